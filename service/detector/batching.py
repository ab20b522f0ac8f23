"""Continuous micro-batching: crops of concurrent requests share one onnxruntime run.

Each of ``streams`` inference threads takes whatever requests are queued (up to
``max_batch`` crops), runs them as one batch and hands each request its slice. Nothing
waits for a batch to fill: a lone request runs at once, and under load the queue fills
while the previous batches run, so batches grow exactly when they pay off. Several
streams keep several cores busy when each run uses few intra-op threads.

With a batching window (``window_s`` > 0) a stream that has its first request keeps
collecting for up to that long, until ``max_batch`` crops: on a GPU a run costs little more for
many crops than for one, so a millisecond or two of waiting buys larger, cheaper batches.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field

import numpy as np

RunBatch = Callable[[np.ndarray], np.ndarray]


@dataclass
class _Request:
    batch: np.ndarray
    result: Future = field(default_factory=Future)


class MicroBatcher:
    """Serializes inference on one thread and merges queued requests into one run."""

    def __init__(self, run_batch: RunBatch, max_batch: int, streams: int = 1, window_s: float = 0.0) -> None:
        self._run_batch = run_batch
        self._max_batch = max_batch
        self._window_s = window_s
        self._queue: queue.SimpleQueue[_Request | None] = queue.SimpleQueue()
        self._carry: _Request | None = None
        self._grouping = threading.Lock()  # one stream at a time forms its group
        self._threads = [
            threading.Thread(target=self._loop, name=f"inference-{i}", daemon=True) for i in range(streams)
        ]
        for thread in self._threads:
            thread.start()

    def run(self, batch: np.ndarray) -> np.ndarray:
        """Heatmaps for ``batch``; blocks the calling (worker) thread until they are ready."""
        request = _Request(batch)
        self._queue.put(request)
        return request.result.result()

    def close(self) -> None:
        for _ in self._threads:
            self._queue.put(None)
        for thread in self._threads:
            thread.join(timeout=10)

    def _loop(self) -> None:
        while (requests := self._next_group()) is not None:
            try:
                outputs = self._run_batch(np.concatenate([r.batch for r in requests]))
            except BaseException as error:  # every waiting request learns of the failure
                for request in requests:
                    request.result.set_exception(error)
                continue
            start = 0
            for request in requests:
                request.result.set_result(outputs[start : start + len(request.batch)])
                start += len(request.batch)

    def _next_group(self) -> list[_Request] | None:
        with self._grouping:
            return self._form_group()

    def _form_group(self) -> list[_Request] | None:
        first = self._carry or self._queue.get()
        self._carry = None
        if first is None:
            return None
        group, size = [first], len(first.batch)
        deadline = time.monotonic() + self._window_s
        while size < self._max_batch:
            try:
                request = self._next_queued(deadline)
            except queue.Empty:
                break
            if request is None:
                self._queue.put(None)  # leave the stop signal for a stream
                break
            if size + len(request.batch) > self._max_batch:
                self._carry = request  # the next group starts with it
                break
            group.append(request)
            size += len(request.batch)
        return group

    def _next_queued(self, deadline: float) -> _Request | None:
        """The next queued request, waiting until ``deadline`` at most (``queue.Empty`` after)."""
        remaining = deadline - time.monotonic()
        return self._queue.get(timeout=remaining) if remaining > 0 else self._queue.get_nowait()
