"""The micro-batcher merges concurrent requests without mixing up their results."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from service.detector.batching import MicroBatcher


class RecordingRun:
    """A real (pure numpy) batch function that records the batch sizes it was given."""

    def __init__(self, gate: threading.Event | None = None) -> None:
        self.sizes: list[int] = []
        self.gate = gate
        self.entered = threading.Event()

    def __call__(self, batch: np.ndarray) -> np.ndarray:
        self.entered.set()
        if self.gate is not None:
            self.gate.wait(5)
        self.sizes.append(len(batch))
        return batch * 2.0 + batch.sum(axis=(1, 2, 3), keepdims=True)


def test_each_caller_gets_its_own_rows_back():
    run = RecordingRun()
    batcher = MicroBatcher(run, max_batch=8)
    rng = np.random.default_rng(0)
    inputs = [rng.random((int(rng.integers(1, 4)), 1, 2, 2)) for _ in range(40)]
    results: list[np.ndarray | None] = [None] * len(inputs)

    def call(i: int) -> None:
        results[i] = batcher.run(inputs[i])

    threads = [threading.Thread(target=call, args=(i,)) for i in range(len(inputs))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    batcher.close()
    sizes = list(run.sizes)
    for given, got in zip(inputs, results, strict=True):
        np.testing.assert_array_equal(got, run(given))
    assert sum(sizes) == sum(len(x) for x in inputs)
    assert max(sizes) <= 8


def test_queued_requests_share_one_run_and_respect_max_batch():
    gate = threading.Event()
    run = RecordingRun(gate)
    batcher = MicroBatcher(run, max_batch=5)
    threads = [threading.Thread(target=batcher.run, args=(np.ones((2, 1, 1, 1)),)) for _ in range(6)]
    threads[0].start()  # nothing runs or waits: it runs on its own thread, held by the gate
    assert run.entered.wait(5), "the first request never reached the model"
    threads[1].start()  # the only stream takes this one, held by the gate too
    while batcher._busy < 2:
        threading.Event().wait(0.01)
    for thread in threads[2:]:  # these four queue up
        thread.start()
    while batcher._queue.qsize() < 4:
        threading.Event().wait(0.01)
    gate.set()
    for thread in threads:
        thread.join()
    batcher.close()
    assert sorted(run.sizes) == [2, 2, 4, 4], f"queued pairs (4 crops) should share runs: {run.sizes}"


def test_a_lone_request_runs_on_its_callers_thread():
    callers: list[str] = []

    def run(batch: np.ndarray) -> np.ndarray:
        callers.append(threading.current_thread().name)
        return batch

    batcher = MicroBatcher(run, max_batch=8, streams=2)
    batcher.run(np.ones((1, 1, 1, 1)))
    batcher.close()
    assert callers == [threading.current_thread().name]


def test_a_failing_run_fails_every_waiting_request():
    def broken(batch: np.ndarray) -> np.ndarray:
        raise RuntimeError("model exploded")

    batcher = MicroBatcher(broken, max_batch=4)
    with pytest.raises(RuntimeError, match="model exploded"):
        batcher.run(np.ones((1, 1, 1, 1)))
    batcher.close()


def test_several_streams_run_batches_in_parallel_and_stop_cleanly():
    started = threading.Barrier(2, timeout=5)

    def run(batch: np.ndarray) -> np.ndarray:
        started.wait()  # only passes if two runs are in flight at once
        return batch + 1

    batcher = MicroBatcher(run, max_batch=1, streams=2)
    results: list[np.ndarray] = []

    def call(value: float) -> None:
        results.append(batcher.run(np.full((1, 1), value)))

    threads = [threading.Thread(target=call, args=(value,)) for value in (1.0, 2.0)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    batcher.close()
    assert sorted(float(r[0, 0]) for r in results) == [2.0, 3.0]
    assert not any(thread.is_alive() for thread in batcher._threads)


def test_a_lone_wide_request_is_split_across_idle_streams_in_parallel():
    both_running = threading.Barrier(2, timeout=5)
    whole = RecordingRun()

    def run(batch: np.ndarray) -> np.ndarray:
        both_running.wait()  # only passes if the two parts run at once
        return whole(batch)

    batcher = MicroBatcher(run, max_batch=8, streams=2, run_wide=lambda batch: -batch)
    given = np.random.default_rng(1).random((5, 1, 2, 2))
    got = batcher.run(given, wide=True)
    batcher.close()
    assert sorted(whole.sizes) == [2, 3], f"5 crops should run as parts of 3 and 2: {whole.sizes}"
    np.testing.assert_array_equal(got, np.concatenate([whole(given[:3]), whole(given[3:])]))


def test_a_wide_request_that_cannot_be_split_runs_wide_and_a_narrow_one_never_does():
    for streams, crops, wide, expected in ((2, 1, True, -1.0), (1, 4, True, -1.0), (2, 4, False, 2.0)):
        batcher = MicroBatcher(lambda batch: batch * 2, max_batch=8, streams=streams, run_wide=lambda b: -b)
        got = batcher.run(np.ones((crops, 1, 1, 1)), wide=wide)
        batcher.close()
        assert got.shape == (crops, 1, 1, 1) and np.all(got == expected), (streams, crops, wide)


def test_a_failing_part_fails_the_split_request():
    def run(batch: np.ndarray) -> np.ndarray:
        if batch[0, 0, 0, 0] > 0:
            raise RuntimeError("part exploded")
        return batch

    batcher = MicroBatcher(run, max_batch=8, streams=2)
    with pytest.raises(RuntimeError, match="part exploded"):
        batcher.run(np.array([0.0, 1.0]).reshape(2, 1, 1, 1), wide=True)
    batcher.close()
