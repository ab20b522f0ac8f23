"""A request alone in the process may run wide; its heatmaps are those of a narrow run."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from service.detector.runtime import Detector
from service.settings import DEFAULT_MODEL_DIR, Settings, usable_cores


@pytest.mark.parametrize("max_batch", [0, 32])
def test_wide_and_narrow_runs_give_the_same_heatmaps(max_batch: int) -> None:
    detector = Detector(DEFAULT_MODEL_DIR, 1, max_batch, streams=2, solo_threads=2)
    try:
        spec = detector.manifest.input
        for crops in (1, 4):
            batch = np.random.default_rng(crops).random((crops, spec.channels, spec.height, spec.width))
            batch = batch.astype(np.float32)
            expected = detector.run_session(batch)
            with detector.computing():
                runs = [detector.run(batch) for _ in range(3)]  # wide first, then narrow, then the faster
            for heatmaps in runs:
                np.testing.assert_allclose(heatmaps, expected, rtol=1e-5, atol=1e-6)
            estimates = detector._ways._estimates[crops].seconds
            assert set(estimates) == {True, False}, "both ways should have been timed"
    finally:
        detector.close()


def test_usable_cores_follow_a_cgroup_quota(tmp_path: Path) -> None:
    cores = len(os.sched_getaffinity(0))
    cpu_max = tmp_path / "cpu.max"
    cpu_max.write_text("max 100000\n")
    assert usable_cores(cpu_max) == cores
    cpu_max.write_text("100000 100000\n")
    assert usable_cores(cpu_max) == 1
    assert usable_cores(tmp_path / "missing") == cores
    # workers share one count of requests (activity.py): a lone one may take every core
    assert Settings(workers=cores, inference_threads=1).solo_threads == cores
    assert Settings(inference_threads=0).solo_threads == 0  # ort's default already takes every core
