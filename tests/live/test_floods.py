"""A polite client stays served beside a flood: >= 99 % of its requests answered, its p99 at most 3x
its quiet p99. The server process and the proxy are the point: real connections from many
addresses of 127.0.0.0/8, the flood driven by a process of its own.

- through the shipped proxy (deploy/haproxy/haproxy.cfg), beside a flood from 100 addresses of one
  /24: the proxy's share per network;
- straight to the service, beside a flood from one address: the service's cap per caller;
- with predict tokens on, beside a flood from 100 /24 networks without tokens (401), and beside a
  flood from another token holder: a caller is its token.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from benchmarks.fleet import haproxy
from benchmarks.load import Flood, polite_client
from tests.live.server import LiveServer
from tests.service_calls import ADMIN_TOKEN

QUIET_S, FLOODED_S, INTERVAL_S = 6.0, 15.0, 0.05
POLITE_TOKEN = "polite-robot-token-0123456789"
FLOOD_TOKEN = "flooding-robot-token-0123456789"


def assert_served_beside(url: str, flood: Flood, token: str | None = None) -> None:
    """The quiet p99 is the larger of the one just before the flood and the one just after it: the
    machine's other work (other tests) weighs on both sides alike."""
    before, statuses = polite_client(url, QUIET_S, INTERVAL_S, token=token)
    with flood:
        flooded, flooded_statuses = polite_client(url, FLOODED_S, INTERVAL_S, token=token)
    after, more = polite_client(url, QUIET_S, INTERVAL_S, token=token)
    assert set(statuses + more) == {200}, statuses + more
    answered = flooded_statuses.count(200) / len(flooded_statuses)
    quiet_p99 = max(np.percentile(before, 99), np.percentile(after, 99))
    flooded_p99 = np.percentile(flooded, 99)
    report = (
        f"polite: {answered:.1%} of {len(flooded_statuses)} answered, p99 {flooded_p99 * 1e3:.0f} ms"
        f" beside the flood against {quiet_p99 * 1e3:.0f} ms quiet; the flood got {dict(flood.statuses)}"
    )
    print(report)
    assert answered >= 0.99, report
    assert flooded_p99 <= 3 * quiet_p99, report


@pytest.fixture(scope="module")
def open_service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    """Predict tokens off; X-Forwarded-For believed from the proxy's address."""
    data = tmp_path_factory.mktemp("open") / "data"
    with LiveServer(data, trusted_proxies="127.0.0.1") as server:
        yield server


@pytest.fixture(scope="module")
def token_service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    folder = tmp_path_factory.mktemp("tokens")
    tokens = folder / "tokens"
    tokens.write_text(f"predict polite:{POLITE_TOKEN}\npredict flood:{FLOOD_TOKEN}\n")
    with LiveServer(folder / "data", admin_token=ADMIN_TOKEN, admin_tokens_file=tokens) as server:
        yield server


def test_a_flood_from_one_network_through_the_shipped_proxy(open_service: LiveServer, tmp_path: Path) -> None:
    one_network = [f"127.0.1.{n}" for n in range(1, 101)]
    with haproxy([open_service.url], tmp_path) as proxy:
        assert_served_beside(proxy, Flood(proxy, 100, addresses=one_network))


def test_a_flood_from_one_address_straight_to_the_service(open_service: LiveServer) -> None:
    assert_served_beside(open_service.url, Flood(open_service.url, 100, addresses=["127.0.2.1"]))


def test_a_tokenless_flood_from_100_networks_beside_a_token_holder(token_service: LiveServer) -> None:
    networks = [f"127.1.{n}.1" for n in range(100)]
    flood = Flood(token_service.url, 100, addresses=networks)
    assert_served_beside(token_service.url, flood, token=POLITE_TOKEN)
    assert set(flood.statuses) <= {401, "error"} and flood.statuses[401], flood.statuses


def test_a_flood_from_another_token_holder(token_service: LiveServer) -> None:
    flood = Flood(token_service.url, 100, addresses=["127.0.3.1"], token=FLOOD_TOKEN)
    assert_served_beside(token_service.url, flood, token=POLITE_TOKEN)
