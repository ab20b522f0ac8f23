"""Concurrent requests run on their own threads, each its crops in one run, on one session."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from service.detector.session import Detector
from service.runtime.settings import DEFAULT_MODEL_DIR


def test_concurrent_runs_each_get_their_own_heatmaps() -> None:
    detector = Detector(DEFAULT_MODEL_DIR, threads=1)
    spec = detector.manifest.input
    rng = np.random.default_rng(0)
    batches = [
        rng.random((crops, spec.channels, spec.height, spec.width), dtype=np.float32)
        for crops in (1, 4, 2, 3) * 4
    ]
    alone = [detector.run(batch) for batch in batches]
    with ThreadPoolExecutor(8) as pool:
        together = list(pool.map(detector.run, batches))
    for expected, heatmaps in zip(alone, together, strict=True):
        np.testing.assert_array_equal(heatmaps, expected)
