"""Overload: a bounded queue and a queue timeout answer 503 + Retry-After, and the server recovers.

One slow request (many instances) holds the only compute slot of a real server while
the others arrive; the server's own gauges in /metrics tell the test when a request is
computing or waiting, so nothing depends on sleeping for the right time.
"""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx

from tests.api.test_predict_batch import Part, image_part, post_batch, request_part
from tests.live.server import LiveServer, metric
from tests.predict_client import instances_of, predict_json, predict_multipart
from tests.samples import Sample, samples_by_image
from tests.service_calls import assert_problem, wait_until

SLOW_INSTANCES = 128
#: longer than the slow request computes on a busy machine (load average 10+ stretched it past the
#: default 10 s), so that a request waiting behind it is answered, not timed out
QUEUE_TIMEOUT_S = 300


def post_in_background(pool: ThreadPoolExecutor, server: LiveServer, image: bytes, instances: list) -> Future:
    def post() -> httpx.Response:
        with httpx.Client(base_url=server.url, timeout=120) as client:
            return predict_json(client, image, {"instances": instances})

    return pool.submit(post)


def hold_the_slot(pool: ThreadPoolExecutor, server: LiveServer, image: bytes, slow: list) -> Future:
    """Post the slow request and return once the server reports it computing."""
    computing = post_in_background(pool, server, image, slow)
    wait_until(lambda: metric(server, "cks_predict_computing") == 1, "the slow request computes")
    return computing


def slow_and_quick(samples: list[Sample]) -> tuple[bytes, list, list]:
    path, group = next(iter(samples_by_image(samples).items()))
    instances = instances_of(group)
    return path.read_bytes(), (instances * SLOW_INSTANCES)[:SLOW_INSTANCES], instances[:1]


@dataclass(frozen=True)
class HeldSlot:
    """A server with one compute slot, held by a slow request; ``quick`` is a small request."""

    server: LiveServer
    pool: ThreadPoolExecutor
    computing: Future
    image: bytes
    quick: list


@contextmanager
def slot_held_by_a_slow_request(
    tmp_path: Path, samples: list[Sample], **settings: object
) -> Iterator[HeldSlot]:
    image, slow, quick = slow_and_quick(samples)
    settings = {
        "max_concurrent_inferences": 1,
        "max_instances": SLOW_INSTANCES,
        "queue_timeout_seconds": QUEUE_TIMEOUT_S,
        **settings,
    }
    with LiveServer(tmp_path / "data", **settings) as server, ThreadPoolExecutor(2) as pool:
        yield HeldSlot(server, pool, hold_the_slot(pool, server, image, slow), image, quick)


def test_a_full_queue_is_refused_at_once_and_the_server_recovers(
    tmp_path: Path, samples: list[Sample]
) -> None:
    with slot_held_by_a_slow_request(tmp_path, samples, max_queued_requests=1) as held:
        server, image, quick, computing = held.server, held.image, held.quick, held.computing
        waiting = post_in_background(held.pool, server, image, quick)
        wait_until(lambda: metric(server, "cks_predict_waiting") == 1, "the second request waits")

        refused = predict_json(server.client, image, {"instances": quick})
        assert not computing.done(), "the slow request ended too soon to test the queue"
        body = assert_problem(refused, 503, "at capacity", "CKS_MAX_QUEUED_REQUESTS", "retry after")
        assert body["title"] == "Overloaded" and refused.headers["retry-after"] == "1"

        assert computing.result().status_code == 200 and waiting.result().status_code == 200
        assert len(computing.result().json()["instances"]) == SLOW_INSTANCES
        assert predict_json(server.client, image, {"instances": quick}).status_code == 200
        assert metric(server, "cks_predict_rejected_total", '{reason="queue_full"}') == 1
        assert metric(server, "cks_predict_in_flight") == 0 and metric(server, "cks_predict_waiting") == 0


def test_a_request_waiting_longer_than_the_queue_timeout_gets_503(
    tmp_path: Path, samples: list[Sample]
) -> None:
    with slot_held_by_a_slow_request(tmp_path, samples, queue_timeout_seconds=0.2) as held:
        server, computing = held.server, held.computing
        timed_out = predict_json(server.client, held.image, {"instances": held.quick})
        assert not computing.done(), "the slow request ended too soon to test the timeout"
        assert_problem(timed_out, 503, "within 0.2 s", "CKS_QUEUE_TIMEOUT_SECONDS")
        assert timed_out.headers["retry-after"] == "1"
        assert computing.result().status_code == 200
        assert metric(server, "cks_predict_rejected_total", '{reason="queue_timeout"}') == 1


def test_admission_counts_images(tmp_path: Path, sample: tuple[bytes, list[dict]]) -> None:
    """Capacity 3 (1 computing + 2 waiting), a slow request computing: a batch takes one
    place per image, so 3 images are refused where 2 are admitted, and 4 can never be."""
    image, instances = sample
    slow = (instances * 1000)[:768]

    def batch_of(count: int) -> list[Part]:
        return [
            part
            for i in range(count)
            for part in (image_part(i, image), request_part(i, {"instances": instances}))
        ]

    # The admitted batch waits for the slow request's slot: on a loaded machine that can take longer
    # than the default queue timeout (10 s), which would turn its 200s into 503s.
    settings = {
        "max_concurrent_inferences": 1,
        "max_queued_requests": 2,
        "max_instances": len(slow),
        "queue_timeout_seconds": 120,
    }
    with LiveServer(tmp_path / "data", **settings) as server, ThreadPoolExecutor(2) as pool:
        computing = hold_the_slot(pool, server, image, slow)

        never = post_batch(server.client, batch_of(4))
        assert_problem(never, 422, "a batch of 4 images needs 4 admission places", "has 3")
        refused = post_batch(server.client, batch_of(3))
        assert_problem(refused, 503, "at capacity", "this batch needs 3 places", "retry after")
        assert refused.headers["retry-after"] == "1"

        def post_two() -> httpx.Response:
            with httpx.Client(base_url=server.url, timeout=120) as client:
                return post_batch(client, batch_of(2))

        admitted: Future = pool.submit(post_two)
        wait_until(lambda: metric(server, "cks_predict_in_flight") == 3, "the batch of 2 holds two places")
        single = predict_multipart(server.client, image, {"instances": instances})
        assert_problem(single, 503, "at capacity")
        assert not computing.done(), "the slow request ended too soon to test admission"

        assert computing.result().status_code == 200
        answer = admitted.result()
        assert answer.status_code == 200 and [i["status"] for i in answer.json()["items"]] == [200, 200]
        assert metric(server, "cks_predict_rejected_total", '{reason="queue_full"}') == 2
        assert metric(server, "cks_predict_in_flight") == 0
