"""Continuous micro-batching: crops of concurrent requests share one onnxruntime run.

Each of ``streams`` inference threads takes whatever requests are queued (up to
``max_batch`` crops), runs them as one batch and hands each request its slice. Nothing
waits for a batch to fill: a lone request runs at once, and under load the queue fills
while the previous batches run, so batches grow exactly when they pay off. Several
streams keep several cores busy when each run uses few intra-op threads.

A request that finds every stream idle and nothing queued runs on its caller's thread (no
hand-off). A request may ask to run ``wide`` (see ``chooser``): if it is alone, its crops are
split across the idle streams, their parts running at once, or, with one crop or no idle
stream, it runs through ``run_wide`` (more intra-op threads). Merged with other requests it
runs as any other.

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
    wide: bool = False  # run on every core it can get when alone


def _split(request: _Request, count: int) -> list[_Request]:
    """``count`` parts of ``request``'s crops; its result is set once every part has one."""
    parts = [_Request(batch) for batch in np.array_split(request.batch, count)]
    pending, lock = [count], threading.Lock()

    def part_done(_: Future) -> None:
        with lock:
            pending[0] -= 1
            if pending[0]:
                return
        try:
            request.result.set_result(np.concatenate([part.result.result() for part in parts]))
        except BaseException as error:
            request.result.set_exception(error)

    for part in parts:
        part.result.add_done_callback(part_done)
    return parts


class MicroBatcher:
    """Serializes inference on one thread and merges queued requests into one run."""

    def __init__(
        self,
        run_batch: RunBatch,
        max_batch: int,
        streams: int = 1,
        window_s: float = 0.0,
        run_wide: RunBatch | None = None,
    ) -> None:
        self._run_batch = run_batch
        self._run_wide = run_wide or run_batch
        self._max_batch = max_batch
        self._streams = streams
        self._window_s = window_s
        self._queue: queue.SimpleQueue[_Request | None] = queue.SimpleQueue()
        self._carry: list[_Request] = []
        self._grouping = threading.Lock()  # one stream at a time forms its group
        self._busy, self._counting = 0, threading.Lock()  # streams running a batch
        self._threads = [
            threading.Thread(target=self._loop, name=f"inference-{i}", daemon=True) for i in range(streams)
        ]
        for thread in self._threads:
            thread.start()

    def run(self, batch: np.ndarray, wide: bool = False) -> np.ndarray:
        """Heatmaps for ``batch``; blocks the calling (worker) thread until they are ready.

        When no stream runs and nothing waits, the caller runs its batch itself: a lone request
        is spared the two thread hand-offs, each a wait for a core on a busy machine."""
        request = _Request(batch, wide=wide)
        if not self._claim_idle():
            self._queue.put(request)
            return request.result.result()
        try:
            self._run_here(request)
        finally:
            with self._counting:
                self._busy -= 1
        return request.result.result()

    def _claim_idle(self) -> bool:
        """Counts the caller as a busy stream if none is busy and nothing is queued (never with a
        batching window: a lone request waits in a stream for others to join it)."""
        with self._counting:
            if self._window_s or self._busy or self._carry or not self._queue.empty():
                return False
            self._busy += 1
            return True

    def _run_here(self, request: _Request) -> None:
        """A wide request of several crops: its first part here, the others to the idle streams."""
        count = min(len(request.batch), self._streams) if request.wide else 1
        if count < 2:
            self._run_group([request])
            return
        first, *rest = _split(request, count)
        for part in rest:
            self._queue.put(part)
        self._run_group([first])

    def close(self) -> None:
        for _ in self._threads:
            self._queue.put(None)
        for thread in self._threads:
            thread.join(timeout=10)

    def _loop(self) -> None:
        while (requests := self._next_group()) is not None:
            try:
                self._run_group(requests)
            finally:
                with self._counting:
                    self._busy -= 1

    def _run_group(self, requests: list[_Request]) -> None:
        run = self._run_wide if len(requests) == 1 and requests[0].wide else self._run_batch
        try:
            outputs = run(np.concatenate([r.batch for r in requests]))
        except BaseException as error:  # every waiting request learns of the failure
            for request in requests:
                request.result.set_exception(error)
            return
        start = 0
        for request in requests:
            request.result.set_result(outputs[start : start + len(request.batch)])
            start += len(request.batch)

    def _next_group(self) -> list[_Request] | None:
        with self._grouping:
            group = self._form_group()
            if group is not None:
                with self._counting:
                    self._busy += 1
                    idle = self._streams - self._busy
                if len(group) == 1 and group[0].wide and self._queue.empty():
                    group = self._spread(group[0], idle)
            return group

    def _spread(self, request: _Request, idle: int) -> list[_Request]:
        """Split a lone wide request across the idle streams; this stream runs the first part.
        (With one crop or no idle stream it stays whole, for ``run_wide``.)"""
        count = min(len(request.batch), idle + 1)
        if count < 2:
            return [request]
        first, *rest = _split(request, count)
        self._carry = rest + self._carry  # the idle streams, waiting for this lock, take them
        return [first]

    def _form_group(self) -> list[_Request] | None:
        first = self._carry.pop(0) if self._carry else self._queue.get()
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
                self._carry.append(request)  # the next group starts with it
                break
            group.append(request)
            size += len(request.batch)
        return group

    def _next_queued(self, deadline: float) -> _Request | None:
        """The next queued request, waiting until ``deadline`` at most (``queue.Empty`` after)."""
        remaining = deadline - time.monotonic()
        return self._queue.get(timeout=remaining) if remaining > 0 else self._queue.get_nowait()
