"""Sliding windows of live values: fixed numpy ring buffers, one per keyed stream. A request is one
vectorized append under a lock held for microseconds; readers copy a window out and compute on it.
"""

from __future__ import annotations

import threading

import numpy as np


class RingWindows:
    """The last ``capacity`` rows of ``width`` floats for each of ``streams`` streams."""

    def __init__(self, streams: int, capacity: int, width: int = 1) -> None:
        if capacity < 1:
            raise ValueError(f"a window holds at least one value, got capacity {capacity}")
        self.capacity = capacity
        self._values = np.full((streams, capacity, width), np.nan)
        self._written = np.zeros(streams, dtype=np.int64)  # rows ever appended, per stream
        self._lock = threading.Lock()

    def append(self, streams: np.ndarray, rows: np.ndarray) -> None:
        """Append ``rows`` (M, width) to their ``streams`` (M,); a stream may repeat."""
        if streams.size == 0:
            return
        rows = rows.reshape(streams.size, -1)
        if np.bincount(streams).max() == 1:  # the common case (one instance per object): no sort
            with self._lock:
                self._values[streams, self._written[streams] % self.capacity] = rows
                self._written[streams] += 1
            return
        order = np.argsort(streams, kind="stable")
        sorted_streams = streams[order]
        starts = np.flatnonzero(np.r_[True, sorted_streams[1:] != sorted_streams[:-1]])
        counts = np.diff(np.r_[starts, sorted_streams.size])
        rank = np.arange(sorted_streams.size) - np.repeat(starts, counts)  # place within its stream
        with self._lock:
            slots = (self._written[sorted_streams] + rank) % self.capacity
            self._values[sorted_streams, slots] = rows[order]
            self._written[sorted_streams[starts]] += counts

    def window(self, stream: int) -> np.ndarray:
        """A copy of the stream's window, (n, width), n = min(rows appended, capacity); unordered."""
        with self._lock:
            filled = min(int(self._written[stream]), self.capacity)
            return self._values[stream, :filled].copy()

    def written(self) -> int:
        """Rows appended so far, all streams together (changes whenever a window does)."""
        with self._lock:
            return int(self._written.sum())
