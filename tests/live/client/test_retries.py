"""The client on a busy or flaky service, over real sockets: 503s retried after Retry-After
(through a proxy that injects them, and through a real server's saturated admission), bounded
attempts ending in typed errors, and connection errors retried only where that is safe."""

from __future__ import annotations

import asyncio
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from keypoint_client import (
    AsyncKeypointClient,
    ConnectionFailed,
    KeypointClient,
    RetryPolicy,
    ServiceUnavailable,
    TooManyRequests,
)
from keypoint_client.retry import retry_after_seconds

from tests.api.in_process import OnLoopback
from tests.api.test_overload import metric
from tests.live.client.faulty_proxy import Drop, FaultyProxy, Unavailable
from tests.live.server import LiveServer, free_port
from tests.predict_client import predict_json
from tests.service_calls import ADMIN_TOKEN, BUSY_MACHINE_MARGIN_S, wait_until

QUICK = RetryPolicy(attempts=3, backoff=0.05)


def test_503s_are_retried_after_retry_after(server: LiveServer, sample) -> None:
    image, instances = sample
    faults = [Unavailable("1"), Unavailable("1")]
    with FaultyProxy(server.url, faults) as proxy, KeypointClient(proxy.url, retry=QUICK) as client:
        result = client.predict(image, instances)
    assert result.to_dict() == predict_json(server.client, image, {"instances": instances}).json()
    assert [s.path for s in proxy.seen] == ["/v1/predict"] * 3
    assert len({s.request_id for s in proxy.seen}) == 1, "one call, one request id, on every attempt"
    waits = [later.at - earlier.at for earlier, later in zip(proxy.seen, proxy.seen[1:], strict=False)]
    assert all(1.0 <= wait < 1.0 + 2 * QUICK.backoff + BUSY_MACHINE_MARGIN_S for wait in waits), waits


def test_429s_are_retried_like_503s_and_end_in_their_own_error(server: LiveServer, sample) -> None:
    image, instances = sample
    busy = Unavailable("0", status=429)
    with FaultyProxy(server.url, [busy]) as proxy, KeypointClient(proxy.url) as client:
        assert client.predict(image, instances).instances
    assert len(proxy.seen) == 2
    with (
        FaultyProxy(server.url, [busy] * 3) as proxy,
        KeypointClient(proxy.url, retry=QUICK) as client,
        pytest.raises(TooManyRequests) as refused,
    ):
        client.predict(image, instances)
    assert refused.value.status == 429 and len(proxy.seen) == QUICK.attempts


def test_attempts_are_bounded_and_end_in_a_typed_error(server: LiveServer, sample) -> None:
    image, instances = sample
    with (
        FaultyProxy(server.url, [Unavailable("0")] * 3) as proxy,
        KeypointClient(proxy.url, retry=QUICK) as client,
        pytest.raises(ServiceUnavailable) as refused,
    ):
        client.predict(image, instances)
    error = refused.value
    assert (error.status, error.title, error.detail) == (503, "Overloaded", "injected by the test's proxy")
    assert error.retry_after == 0.0 and error.request_id == proxy.seen[0].request_id
    assert len(proxy.seen) == QUICK.attempts

    # A Retry-After beyond the policy's max_retry_after is not waited for.
    with FaultyProxy(server.url, [Unavailable("3600")]) as proxy, KeypointClient(proxy.url) as client:
        started = time.monotonic()
        with pytest.raises(ServiceUnavailable) as later:
            client.model()
    assert later.value.retry_after == 3600 and len(proxy.seen) == 1
    assert time.monotonic() - started < BUSY_MACHINE_MARGIN_S  # not the hour it asked for


def test_connection_errors_are_retried_where_safe(server: LiveServer, sample, samples_dir: Path) -> None:
    image, instances = sample
    nowhere = KeypointClient(f"http://127.0.0.1:{free_port()}", token=ADMIN_TOKEN, retry=QUICK)
    for call in (lambda: nowhere.model(), lambda: nowhere.activate(1, reason="x")):  # nothing was sent
        with pytest.raises(ConnectionFailed, match="ConnectError.*after 3 attempts"):
            call()

    with FaultyProxy(server.url, [Drop()]) as proxy, KeypointClient(proxy.url, token=ADMIN_TOKEN) as client:
        assert client.predict(image, instances).instances  # idempotent: asked again
        assert [s.path for s in proxy.seen] == ["/v1/predict"] * 2

        versions = client.versions().versions
        proxy.faults.append(Drop())
        with pytest.raises(ConnectionFailed, match="not retried: the call is not idempotent"):
            client.upload_calibration(samples_dir)  # the upload may have arrived: not sent twice
        assert [s.path for s in proxy.seen[3:]] == ["/v1/admin/calibrations"]
        assert client.versions().versions == versions


def test_the_client_waits_out_a_saturated_server(tmp_path: Path, sample) -> None:
    """A real server with one place, held by a slow request: the client's predict is refused
    with 503 + Retry-After by admission control, waits, and is answered."""
    image, instances = sample
    slow = (instances * 1000)[:256]  # about a second of computing quiet, 10+ s on a busy machine
    settings = {"max_concurrent_inferences": 1, "max_queued_requests": 0}
    fixed = {"MAX_INSTANCES": len(slow)}
    with OnLoopback(tmp_path / "data", fixed, **settings) as server, ThreadPoolExecutor(1) as pool:
        computing = pool.submit(predict_json, server.client, image, {"instances": slow})
        wait_until(lambda: metric(server, "cks_predict_computing") == 1, "the slow request computes")
        with KeypointClient(server.url, retry=RetryPolicy(attempts=60, backoff=0.1)) as client:
            result = client.predict(image, instances)
        assert metric(server, "cks_predict_rejected_total", '{reason="queue_full"}') >= 1
        assert computing.result().status_code == 200
    assert len(result.instances) == len(instances)


def test_the_asyncio_client_retries_the_same_way(server: LiveServer, sample) -> None:
    image, instances = sample

    async def predict(url: str) -> list[int]:
        async with AsyncKeypointClient(url, retry=QUICK) as client:
            result = await client.predict(image, instances)
        return [len(instance.keypoints) for instance in result.instances]

    with FaultyProxy(server.url, [Unavailable("0"), Drop()]) as proxy:
        assert all(asyncio.run(predict(proxy.url)))
    assert len(proxy.seen) == 3 and len({s.request_id for s in proxy.seen}) == 1


def test_retry_after_and_backoff() -> None:
    assert retry_after_seconds("2") == 2.0 and retry_after_seconds(None) is None
    assert retry_after_seconds("soon") is None
    assert retry_after_seconds("Wed, 21 Oct 2015 07:28:00 GMT") == 0.0  # a date past
    policy = RetryPolicy(backoff=1.0, max_backoff=3.0)
    assert all(0 <= policy.delay(retry, None) <= min(3.0, 2 ** (retry - 1)) for retry in (1, 2, 3, 4, 5))
    assert all(5.0 <= policy.delay(3, 5.0) <= 8.0 for _ in range(20))
    with pytest.raises(ValueError, match="at least 1"):
        RetryPolicy(attempts=0)
