"""Who a predict request comes from, for fair admission (``service.api.http.admission``).

A client is, in this order: the admin operator whose token the request carries (``operator
<name>``); else the value of ``CKS_CLIENT_HEADER`` when the connection comes from one of
``CKS_TRUSTED_PROXIES`` (for a list such as ``X-Forwarded-For``, its last entry that is not a
trusted proxy: the one the nearest trusted proxy saw); else the connection's address. A header
from any other peer is ignored: a client could otherwise name itself anew on each request.

An address stands for its network of ``prefixes`` (IPv4, IPv6; CKS_CLIENT_IPV4_PREFIX,
CKS_CLIENT_IPV6_PREFIX; each address by default). Every client belongs to a network of
``network_prefixes`` (CKS_CLIENT_NETWORK_IPV4_PREFIX, CKS_CLIENT_NETWORK_IPV6_PREFIX; a /24 and a
/64 by default): admission shares first between networks, then between the clients of one, so
that a flood spread over the 100 addresses of one network holds one network's share beside a
client of another. A client that is not an address (an operator, a header that names no
address) is a network of its own.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable, Mapping
from typing import NamedTuple

from service.infra.operators import operator_named


class Client(NamedTuple):
    """Who asks (``name``: an operator, an address or a network) and the network it belongs to."""

    name: str
    network: str


class ClientKeys:
    """The client of a request, from its peer address and headers."""

    def __init__(
        self,
        operators: dict[str, str],
        header: str | None = None,
        trusted_proxies: Iterable[str] = (),
        prefixes: tuple[int, int] = (32, 128),
        network_prefixes: tuple[int, int] = (24, 64),
    ) -> None:
        self._operators, self._header = operators, header.lower() if header else None
        self._trusted = tuple(ipaddress.ip_network(proxy, strict=False) for proxy in trusted_proxies)
        self._prefixes = prefixes
        self._network_prefixes = tuple(map(min, prefixes, network_prefixes))  # never within a client

    def of(self, peer: str | None, headers: Mapping[str, str]) -> Client:
        scheme, _, token = headers.get("authorization", "").partition(" ")
        if self._operators and scheme.lower() == "bearer" and token:
            name = operator_named(self._operators, token.strip())
            if name is not None:
                return Client(f"operator {name}", f"operator {name}")
        if self._header and peer and self._is_trusted(peer):
            entries = [entry.strip() for entry in headers.get(self._header, "").split(",") if entry.strip()]
            if entries:
                return self._client(
                    next((entry for entry in reversed(entries) if not self._is_trusted(entry)), entries[0])
                )
        return self._client(peer) if peer else Client("unknown", "unknown")

    def _client(self, address: str) -> Client:
        try:
            ip = ipaddress.ip_address(address)
        except ValueError:
            return Client(address, address)
        return Client(_within(ip, self._prefixes), _within(ip, self._network_prefixes))

    def _is_trusted(self, address: str) -> bool:
        try:
            ip = ipaddress.ip_address(address)
        except ValueError:
            return False
        return any(ip in network for network in self._trusted)


def _within(ip: ipaddress.IPv4Address | ipaddress.IPv6Address, prefixes: tuple[int, ...]) -> str:
    """The address itself, or its network where the prefix for its version is shorter."""
    prefix = prefixes[0] if ip.version == 4 else prefixes[1]
    return (
        str(ip) if prefix == ip.max_prefixlen else str(ipaddress.ip_network(f"{ip}/{prefix}", strict=False))
    )
