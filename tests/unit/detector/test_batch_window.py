"""The batching window (CKS_BATCH_WINDOW_MS): a run waits that long for more crops, never longer
than it takes to fill the batch, and every caller still gets its own rows."""

from __future__ import annotations

import threading
import time

import numpy as np

from service.detector.batching import MicroBatcher


class SizeRecorder:
    """A real batch function (pure numpy) that records the batch sizes it was given."""

    def __init__(self) -> None:
        self.sizes: list[int] = []

    def __call__(self, batch: np.ndarray) -> np.ndarray:
        self.sizes.append(len(batch))
        return batch * 3.0


def call_in_thread(batcher: MicroBatcher, batch: np.ndarray) -> tuple[threading.Thread, list[np.ndarray]]:
    result: list[np.ndarray] = []
    thread = threading.Thread(target=lambda: result.append(batcher.run(batch)))
    thread.start()
    return thread, result


def test_a_request_arriving_within_the_window_joins_the_run() -> None:
    run = SizeRecorder()
    batcher = MicroBatcher(run, max_batch=8, window_s=5.0)
    first, second = np.ones((1, 1, 2, 2)), np.full((2, 1, 2, 2), 2.0)
    thread_a, result_a = call_in_thread(batcher, first)
    time.sleep(0.1)  # the stream holds the first request and waits for more
    thread_b, result_b = call_in_thread(batcher, second)
    thread_a.join(10)
    thread_b.join(10)
    batcher.close()
    assert run.sizes == [3]
    np.testing.assert_array_equal(result_a[0], first * 3.0)
    np.testing.assert_array_equal(result_b[0], second * 3.0)


def test_a_full_batch_runs_without_waiting_out_the_window() -> None:
    run = SizeRecorder()
    batcher = MicroBatcher(run, max_batch=2, window_s=600.0)
    threads = [call_in_thread(batcher, np.ones((1, 1, 2, 2)))[0] for _ in range(2)]
    for thread in threads:
        thread.join(60)
    assert not any(thread.is_alive() for thread in threads), "the full batch waited for the window"
    assert run.sizes == [2]
    batcher.close()


def test_a_lone_request_runs_when_the_window_closes() -> None:
    run = SizeRecorder()
    batcher = MicroBatcher(run, max_batch=8, window_s=0.05)
    np.testing.assert_array_equal(batcher.run(np.ones((1, 1, 2, 2))), np.full((1, 1, 2, 2), 3.0))
    assert run.sizes == [1]
    batcher.close()


def test_close_during_a_window_answers_the_waiting_request_and_stops() -> None:
    run = SizeRecorder()
    batcher = MicroBatcher(run, max_batch=8, streams=2, window_s=600.0)
    thread, result = call_in_thread(batcher, np.ones((1, 1, 2, 2)))
    time.sleep(0.1)
    batcher.close()
    thread.join(60)
    assert not thread.is_alive() and run.sizes == [1]
    np.testing.assert_array_equal(result[0], np.full((1, 1, 2, 2), 3.0))
