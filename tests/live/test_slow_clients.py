"""Slow clients cannot hold the service (issue 13 item 2), against real servers over real sockets.

A predict request takes an admission place only once its body has arrived; until then its
bytes count against CKS_MAX_RECEIVING_BYTES, and a body that arrives later than
CKS_REQUEST_READ_TIMEOUT_SECONDS, or slower than CKS_MIN_BODY_BYTES_PER_SECOND after
CKS_BODY_RATE_GRACE_SECONDS, gets 408. A request head must arrive within
CKS_HEADER_READ_TIMEOUT_SECONDS, an upload within CKS_UPLOAD_READ_TIMEOUT_SECONDS, and at most
CKS_MAX_CONNECTIONS connections are served.
"""

from __future__ import annotations

import json
import socket
import statistics
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest

from benchmarks.faults_clients import SLOW_BODY_HEAD, SlowClients, predict_latencies
from tests.live.server import LiveServer, metric, read_until_closed
from tests.predict_client import predict_json
from tests.service_calls import ADMIN_TOKEN, BUSY_MACHINE_MARGIN_S, assert_problem, wait_until

PACED = {
    "max_concurrent_inferences": 1,
    "max_queued_requests": 0,
    "request_read_timeout_seconds": 3,
    "body_rate_grace_seconds": 1,
    "min_body_bytes_per_second": 1000,
    "header_read_timeout_seconds": 1,
    "upload_read_timeout_seconds": 2,
    "max_receiving_bytes": 400_000,
}
HEAD_TIMEOUT_S = PACED["header_read_timeout_seconds"]


@pytest.fixture(scope="module")
def paced(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    """One compute place, no queue, short timeouts."""
    data = tmp_path_factory.mktemp("paced") / "data"
    with LiveServer(data, admin_token=ADMIN_TOKEN, **PACED) as server:
        yield server


def connect(server: LiveServer) -> socket.socket:
    return socket.create_connection(("127.0.0.1", server.port), timeout=30)


def answer_and_time(connection: socket.socket) -> tuple[str, float]:
    started = time.monotonic()
    return read_until_closed(connection), time.monotonic() - started


def test_a_body_still_arriving_holds_no_place(paced: LiveServer, sample: tuple[bytes, list]) -> None:
    """The only place serves request after request while a body is missing, until its 408."""
    image, instances = sample[0], sample[1][:1]  # one instance: the smallest request
    statuses = []
    with connect(paced) as slow, ThreadPoolExecutor(1) as pool:
        slow.sendall(SLOW_BODY_HEAD + b'{"instances": [' + b" " * 5000)  # then nothing: 5 s at 1000 B/s
        # its place is checked when its head arrives: the loop below must not be holding it then
        wait_until(lambda: metric(paced, "cks_predict_receiving_bytes") > 0, "the slow body is arriving")
        answered = pool.submit(read_until_closed, slow)
        while not answered.done():
            statuses.append(predict_json(paced.client, image, {"instances": instances}).status_code)
        answer = answered.result()
    assert len(statuses) >= 5 and set(statuses) == {200}, statuses
    assert answer.startswith("HTTP/1.1 408"), answer
    assert "CKS_REQUEST_READ_TIMEOUT_SECONDS" in answer and "connection: close" in answer.lower()
    assert metric(paced, "cks_predict_rejected_total", '{reason="queue_full"}') == 0


def test_a_trickled_body_is_cut_at_the_minimum_rate(paced: LiveServer) -> None:
    with connect(paced) as slow:
        slow.sendall(SLOW_BODY_HEAD)
        started = time.monotonic()
        try:
            while time.monotonic() - started < 10:  # 50 bytes a second, against 1000 required
                slow.sendall(b" " * 5)
                time.sleep(0.1)
        except OSError:
            pass  # closed by the server
        answer = read_until_closed(slow)
        elapsed = time.monotonic() - started
    assert answer.startswith("HTTP/1.1 408"), answer
    body = json.loads(answer.split("\r\n\r\n", 1)[1])
    assert "CKS_MIN_BODY_BYTES_PER_SECOND" in body["detail"] and "bytes/s" in body["detail"], body
    assert "CKS_REQUEST_READ_TIMEOUT_SECONDS" not in body["detail"], "the rate, not the 3 s timeout, decides"
    assert elapsed < PACED["request_read_timeout_seconds"] + BUSY_MACHINE_MARGIN_S, elapsed


def test_a_late_request_head_gets_408_and_its_connection_closed(paced: LiveServer) -> None:
    for first_bytes in (b"", b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: "):
        with connect(paced) as slow:
            slow.sendall(first_bytes)
            answer, elapsed = answer_and_time(slow)
        assert answer.startswith("HTTP/1.1 408"), answer
        head, body = answer.split("\r\n\r\n", 1)
        assert "content-type: application/problem+json" in head and "connection: close" in head, head
        problem = json.loads(body)
        assert problem["status"] == 408 and "CKS_HEADER_READ_TIMEOUT_SECONDS" in problem["detail"], problem
        assert 0.5 < elapsed < HEAD_TIMEOUT_S + BUSY_MACHINE_MARGIN_S, elapsed


def test_a_kept_alive_connection_gets_the_same_head_timeout(paced: LiveServer) -> None:
    with connect(paced) as connection:
        connection.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        first = b""
        while not first.endswith(b"}"):  # the whole first response (head and JSON body)
            first += connection.recv(65536)
        assert first.startswith(b"HTTP/1.1 200"), first
        time.sleep(0.8)  # idle, within uvicorn's keep-alive timeout: longer than the head timeout
        connection.sendall(b"GET /healthz HTTP/1.1\r\n")  # the next request's head, unfinished
        answer, elapsed = answer_and_time(connection)
    assert answer.startswith("HTTP/1.1 408"), answer
    assert 0.5 < elapsed < HEAD_TIMEOUT_S + BUSY_MACHINE_MARGIN_S, elapsed


def test_bodies_being_received_share_a_byte_budget(paced: LiveServer, sample: tuple[bytes, list]) -> None:
    image, instances = sample[0], sample[1][:1]  # one instance: the smallest request
    with connect(paced) as large:
        large.sendall(SLOW_BODY_HEAD.replace(b"100000", b"900000") + b" " * 350_000)
        wait_until(lambda: metric(paced, "cks_predict_receiving_bytes") > 0, "the large body is arriving")

        responses = []

        def refused() -> bool:
            responses.append(predict_json(paced.client, image, {"instances": instances}))
            assert responses[-1].status_code in (200, 503), responses[-1].text
            return responses[-1].status_code == 503

        wait_until(refused, "a body that does not fit beside the large one's 350 kB is refused")
        response = responses[-1]
        body = assert_problem(response, 503, "CKS_MAX_RECEIVING_BYTES", "retry after")
        assert body["title"] == "Overloaded" and response.headers["retry-after"] == "1"
        assert read_until_closed(large).startswith("HTTP/1.1 408")  # the read timeout ends it
    assert predict_json(paced.client, image, {"instances": instances}).status_code == 200
    assert metric(paced, "cks_predict_rejected_total", '{reason="receiving_budget"}') >= 1


def test_a_slow_upload_gets_408_and_leaves_nothing(paced: LiveServer) -> None:
    with connect(paced) as slow:
        slow.sendall(
            b"POST /v1/admin/calibrations HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/zip\r\n"
            b"Authorization: Bearer "
            + ADMIN_TOKEN.encode()
            + b"\r\nContent-Length: 10000000\r\n\r\n"
            + b"PK"
            + bytes(20_000)
        )  # then nothing more: fast enough for the rate, too slow for the 2 s timeout
        answer, elapsed = answer_and_time(slow)
    assert answer.startswith("HTTP/1.1 408"), answer
    assert "CKS_UPLOAD_READ_TIMEOUT_SECONDS" in answer, answer
    assert 1.5 < elapsed < PACED["upload_read_timeout_seconds"] + BUSY_MACHINE_MARGIN_S, elapsed
    wait_until(lambda: paced.upload_workspaces() == [], "the partial upload is removed")


def test_connections_beyond_the_limit_get_503(tmp_path: Path) -> None:
    def status() -> int:
        with httpx.Client(base_url=server.url, timeout=10) as client:  # a connection of its own
            return client.get("/healthz").status_code

    with LiveServer(tmp_path / "data", max_connections=3, header_read_timeout_seconds=60) as server:
        server.client.close()  # the connection it kept alive since start-up
        idle = [connect(server) for _ in range(2)]
        try:
            wait_until(lambda: status() == 200, "a 3rd connection is served")
            idle.append(connect(server))
            wait_until(lambda: status() == 503, "a 4th connection is refused")
            idle.pop().close()
            wait_until(lambda: status() == 200, "a 3rd connection is served again")
        finally:
            for connection in idle:
                connection.close()


@pytest.mark.slow
def test_a_hundred_slow_bodies_and_a_hundred_slow_heads_do_not_hold_the_service(tmp_path: Path) -> None:
    """A normal client keeps its latency beside 200 trickling connections, which are cut after the
    rate's grace period (bodies) and the head timeout (heads). Those are 3x their defaults (5 and
    10 s), so that the normal client is done before the cuts even on a busy machine."""
    grace_s, head_s = 15.0, 30.0
    settings = {"body_rate_grace_seconds": grace_s, "header_read_timeout_seconds": head_s}
    with LiveServer(tmp_path / "data", **settings) as server:
        predict_latencies(server.url, 5)  # warm-up
        alone, statuses = predict_latencies(server.url, 20)
        assert set(statuses) == {200}
        with SlowClients(server.port, bodies=100, heads=100) as slow:
            beside, statuses = predict_latencies(server.url, 20)
            assert slow.open_count() == 200, "the slow clients were cut before the normal client was done"
            assert set(statuses) == {200}, statuses
            assert metric(server, "cks_predict_in_flight") == 0, "a slow body holds an admission place"
            closed = slow.wait_closed(timeout=head_s + BUSY_MACHINE_MARGIN_S)
            assert closed, f"{slow.open_count()} slow connections still open"
        # held by the slow ones, its requests would wait seconds (until the cuts); noise is less
        assert statistics.median(beside) <= 2 * statistics.median(alone) + 1.0, (alone, beside)
        for connection in slow.of("body"):
            assert connection.status == 408 and b"CKS_MIN_BODY_BYTES_PER_SECOND" in connection.answer
            assert grace_s - 0.5 < connection.closed_after < grace_s + BUSY_MACHINE_MARGIN_S, connection
        for connection in slow.of("head"):
            assert connection.status == 408 and b"CKS_HEADER_READ_TIMEOUT_SECONDS" in connection.answer
            assert head_s - 0.5 < connection.closed_after < head_s + BUSY_MACHINE_MARGIN_S, connection
        assert metric(server, "cks_predict_rejected_total", '{reason="queue_full"}') == 0
