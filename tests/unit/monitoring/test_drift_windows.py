"""Ring windows against a plain model: per stream, the last ``capacity`` values appended."""

from __future__ import annotations

import threading
from collections import deque

import numpy as np
import pytest

from service.monitoring.windows import RingWindows


def test_windows_hold_the_last_values_of_each_stream():
    rng = np.random.default_rng(5)
    streams, capacity = 6, 7
    windows = RingWindows(streams, capacity)
    model = [deque(maxlen=capacity) for _ in range(streams)]
    appended = 0
    for _ in range(300):
        rows = rng.integers(0, streams, size=int(rng.integers(1, 12)))  # streams repeat within a call
        values = rng.normal(size=rows.size)
        windows.append(rows, values[:, None])
        appended += rows.size
        for stream, value in zip(rows, values, strict=True):
            model[stream].append(value)
        for stream in range(streams):
            assert sorted(windows.window(stream)[:, 0]) == sorted(model[stream])
    assert windows.written() == appended


def test_written_counts_every_row():
    windows = RingWindows(3, 4, width=2)
    windows.append(np.array([0, 0, 2]), np.arange(6.0).reshape(3, 2))
    windows.append(np.array([], dtype=int), np.empty((0, 2)))  # a request without rows
    assert windows.written() == 3
    assert windows.window(0).tolist() == [[0.0, 1.0], [2.0, 3.0]]
    assert windows.window(1).shape == (0, 2)


def test_concurrent_appends_lose_nothing():
    windows = RingWindows(2, 100_000)

    def append_many() -> None:
        for _ in range(500):
            windows.append(np.array([0, 1, 1]), np.ones((3, 1)))

    threads = [threading.Thread(target=append_many) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert windows.window(0).shape[0] == 2000 and windows.window(1).shape[0] == 4000


def test_capacity_must_be_positive():
    with pytest.raises(ValueError, match="at least one value"):
        RingWindows(1, 0)
