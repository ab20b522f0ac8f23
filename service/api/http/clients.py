"""Who a predict request comes from, for fair admission (``service.api.http.admission``).

A client is, in this order: the admin operator whose token the request carries (``operator
<name>``); else the value of ``CKS_CLIENT_HEADER`` when the connection comes from one of
``CKS_TRUSTED_PROXIES`` (for a list such as ``X-Forwarded-For``, its last entry that is not a
trusted proxy: the one the nearest trusted proxy saw); else the connection's address. A header
from any other peer is ignored: a client could otherwise name itself anew on each request.

An address stands for its network of ``prefixes`` (IPv4, IPv6; CKS_CLIENT_IPV4_PREFIX,
CKS_CLIENT_IPV6_PREFIX): with 24, the 100 addresses of a flood spread over one /24 are one
client, held to one client's share, beside a client of another network.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable, Mapping

from service.infra.operators import operator_named

_Network = ipaddress.IPv4Network | ipaddress.IPv6Network


class ClientKeys:
    """The client key of a request, from its peer address and headers."""

    def __init__(
        self,
        operators: dict[str, str],
        header: str | None = None,
        trusted_proxies: Iterable[str] = (),
        prefixes: tuple[int, int] = (32, 128),
    ) -> None:
        self._operators, self._header = operators, header.lower() if header else None
        self._trusted = tuple(ipaddress.ip_network(proxy, strict=False) for proxy in trusted_proxies)
        self._prefixes = prefixes

    def of(self, peer: str | None, headers: Mapping[str, str]) -> str:
        scheme, _, token = headers.get("authorization", "").partition(" ")
        if self._operators and scheme.lower() == "bearer" and token:
            name = operator_named(self._operators, token.strip())
            if name is not None:
                return f"operator {name}"
        if self._header and peer and self._is_trusted(peer):
            entries = [entry.strip() for entry in headers.get(self._header, "").split(",") if entry.strip()]
            if entries:
                return self._network(
                    next((entry for entry in reversed(entries) if not self._is_trusted(entry)), entries[0])
                )
        return self._network(peer) if peer else "unknown"

    def _network(self, address: str) -> str:
        """The address itself, or its network where a prefix is shorter than the address."""
        try:
            ip = ipaddress.ip_address(address)
        except ValueError:
            return address
        prefix = self._prefixes[0] if ip.version == 4 else self._prefixes[1]
        return (
            address
            if prefix == ip.max_prefixlen
            else str(ipaddress.ip_network(f"{ip}/{prefix}", strict=False))
        )

    def _is_trusted(self, address: str) -> bool:
        try:
            ip = ipaddress.ip_address(address)
        except ValueError:
            return False
        return any(ip in network for network in self._trusted)
