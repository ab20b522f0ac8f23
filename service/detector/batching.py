"""Continuous micro-batching: crops of concurrent requests share one onnxruntime run.

One inference thread takes whatever requests are queued (up to ``max_batch`` crops),
runs them as one batch and hands each request its slice. Nothing waits for a batch to
fill: a lone request runs at once, and under load the queue fills while the previous
batch runs, so batches grow exactly when they pay off.
"""

from __future__ import annotations

import queue
import threading
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

    def __init__(self, run_batch: RunBatch, max_batch: int) -> None:
        self._run_batch = run_batch
        self._max_batch = max_batch
        self._queue: queue.SimpleQueue[_Request | None] = queue.SimpleQueue()
        self._carry: _Request | None = None
        self._thread = threading.Thread(target=self._loop, name="inference", daemon=True)
        self._thread.start()

    def run(self, batch: np.ndarray) -> np.ndarray:
        """Heatmaps for ``batch``; blocks the calling (worker) thread until they are ready."""
        request = _Request(batch)
        self._queue.put(request)
        return request.result.result()

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join(timeout=10)

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
        first = self._carry or self._queue.get()
        self._carry = None
        if first is None:
            return None
        group, size = [first], len(first.batch)
        while size < self._max_batch:
            try:
                request = self._queue.get_nowait()
            except queue.Empty:
                break
            if request is None or size + len(request.batch) > self._max_batch:
                self._carry = request  # run it (or stop) after this group
                break
            group.append(request)
            size += len(request.batch)
        return group
