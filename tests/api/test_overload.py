"""Overload in process: a bounded queue and a wait for a slot answer 503 + Retry-After, a batch
takes a place per image, and the service recovers. One slow request (many instances) holds the
only compute slot while others arrive from other threads; the service's own gauges tell the test
when a request computes or waits, so nothing depends on sleeping for the right time."""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx

from tests.api.in_process import InProcess, OnLoopback
from tests.api.test_operations import metric_samples
from tests.api.test_predict_batch import Part, image_part, post_batch, request_part
from tests.predict_client import instances_of, predict_json
from tests.samples import Sample, samples_by_image
from tests.service_calls import assert_problem, wait_until

SLOW_INSTANCES = 256


def metric(service: InProcess | OnLoopback, name: str, labels: str = "") -> float:
    return metric_samples(service.client.get("/metrics").text, name).get(labels, 0.0)


@dataclass(frozen=True)
class HeldSlot:
    """A service with one compute slot, held by a slow request; ``quick`` is a small request."""

    service: InProcess
    pool: ThreadPoolExecutor
    computing: Future
    image: bytes
    quick: list

    def post(self, instances: list) -> Future:
        return post(self.pool, self.service, self.image, instances)


def post(pool: ThreadPoolExecutor, service: InProcess, image: bytes, instances: list) -> Future:
    return pool.submit(predict_json, service.client, image, {"instances": instances})


@contextmanager
def slot_held_by_a_slow_request(
    tmp_path: Path, samples: list[Sample], queue_timeout: float = 300, **settings: object
) -> Iterator[HeldSlot]:
    path, group = next(iter(samples_by_image(samples).items()))
    instances = instances_of(group)
    slow = (instances * SLOW_INSTANCES)[:SLOW_INSTANCES]
    fixed = {"MAX_INSTANCES": SLOW_INSTANCES, "QUEUE_TIMEOUT_SECONDS": queue_timeout}
    with (
        InProcess(tmp_path / "data", fixed, max_concurrent_inferences=1, **settings) as service,
        ThreadPoolExecutor(2) as pool,
    ):
        image = path.read_bytes()
        held = HeldSlot(service, pool, post(pool, service, image, slow), image, instances[:1])
        wait_until(lambda: metric(service, "cks_predict_computing") == 1, "the slow request computes")
        yield held


def test_a_full_queue_is_refused_at_once_and_the_service_recovers(tmp_path: Path, samples: list) -> None:
    with slot_held_by_a_slow_request(tmp_path, samples, max_queued_requests=1) as held:
        service, computing = held.service, held.computing
        rejected = metric(service, "cks_predict_rejected_total", '{reason="queue_full"}')
        waiting = held.post(held.quick)
        wait_until(lambda: metric(service, "cks_predict_waiting") == 1, "the second request waits")

        refused = predict_json(service.client, held.image, {"instances": held.quick})
        assert not computing.done(), "the slow request ended too soon to test the queue"
        body = assert_problem(refused, 503, "at capacity", "CKS_MAX_QUEUED_REQUESTS", "retry after")
        assert body["title"] == "Overloaded" and refused.headers["retry-after"] == "1"

        assert computing.result().status_code == 200 and waiting.result().status_code == 200
        assert len(computing.result().json()["instances"]) == SLOW_INSTANCES
        assert predict_json(service.client, held.image, {"instances": held.quick}).status_code == 200
        assert metric(service, "cks_predict_rejected_total", '{reason="queue_full"}') == rejected + 1
        assert metric(service, "cks_predict_in_flight") == 0 and metric(service, "cks_predict_waiting") == 0


def test_a_request_waiting_longer_than_the_queue_timeout_gets_503(tmp_path: Path, samples: list) -> None:
    with slot_held_by_a_slow_request(tmp_path, samples, queue_timeout=0.2) as held:
        timed_out = predict_json(held.service.client, held.image, {"instances": held.quick})
        assert not held.computing.done(), "the slow request ended too soon to test the timeout"
        assert_problem(timed_out, 503, "no compute slot became free within 0.2 s", "retry after 1 s")
        assert timed_out.headers["retry-after"] == "1"
        assert held.computing.result().status_code == 200


def test_a_batch_takes_a_place_per_image(tmp_path: Path, samples: list) -> None:
    """Capacity 3 (1 computing + 2 waiting), a slow request computing: 3 images are refused where 2
    are admitted, and 4 can never be."""
    with slot_held_by_a_slow_request(tmp_path, samples, max_queued_requests=2) as held:
        service = held.service

        def batch_of(count: int) -> list[Part]:
            parts = (
                (image_part(i, held.image), request_part(i, {"instances": held.quick})) for i in range(count)
            )
            return [part for pair in parts for part in pair]

        never = post_batch(service.client, batch_of(4))
        assert_problem(never, 422, "a batch of 4 images needs 4 admission places", "has 3")
        refused = post_batch(service.client, batch_of(3))
        assert_problem(refused, 503, "at capacity", "this batch needs 3 places", "retry after")
        admitted: Future[httpx.Response] = held.pool.submit(post_batch, service.client, batch_of(2))
        wait_until(lambda: metric(service, "cks_predict_in_flight") == 3, "the batch of 2 holds two places")
        assert_problem(
            predict_json(service.client, held.image, {"instances": held.quick}), 503, "at capacity"
        )
        assert not held.computing.done(), "the slow request ended too soon to test admission"
        assert held.computing.result().status_code == 200
        answer = admitted.result()
        assert answer.status_code == 200 and [i["status"] for i in answer.json()["items"]] == [200, 200]
        assert metric(service, "cks_predict_in_flight") == 0
