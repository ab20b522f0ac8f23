"""Concurrent requests run on their own threads, each its crops in one run; a request alone in
the process runs on every usable core, with the same heatmaps to the bit."""

from __future__ import annotations

import os
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from service.detector.manifest import MODEL_FILENAME
from service.detector.session import Detector, create_session, usable_cores
from service.infra.settings import DEFAULT_MODEL_DIR


@pytest.fixture(scope="module")
def on_every_core() -> Iterator[int]:
    """The machine's cores for this module (a test worker keeps to one: tests/conftest.py)."""
    kept = os.sched_getaffinity(0)
    os.sched_setaffinity(0, range(os.cpu_count() or 1))
    try:
        yield usable_cores()
    finally:
        os.sched_setaffinity(0, kept)


@pytest.fixture(scope="module")
def detector(on_every_core: int) -> Detector:
    return Detector(DEFAULT_MODEL_DIR, threads=1)


def batches(detector: Detector) -> list[np.ndarray]:
    spec = detector.manifest.input
    rng = np.random.default_rng(0)
    return [
        rng.random((crops, spec.channels, spec.height, spec.width), dtype=np.float32)
        for crops in (1, 4, 2, 3) * 4
    ]


def test_concurrent_runs_each_get_their_own_heatmaps(detector: Detector) -> None:
    alone = [detector.run(batch) for batch in batches(detector)]
    with ThreadPoolExecutor(8) as pool:
        together = list(pool.map(detector.run, batches(detector)))
    for expected, heatmaps in zip(alone, together, strict=True):
        np.testing.assert_array_equal(heatmaps, expected)


def test_a_lone_request_runs_wide_and_answers_as_a_request_among_others(
    detector: Detector, on_every_core: int
) -> None:
    assert detector.alone_threads == on_every_core  # threads=1: one core, or every one
    with detector.computing():
        wide = [detector.run(batch) for batch in batches(detector)]
        with detector.computing():  # a second request: each run has CKS_INFERENCE_THREADS
            narrow = [detector.run(batch) for batch in batches(detector)]
    for a, b in zip(wide, narrow, strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_session_without_spinning_tells_onnxruntime_so() -> None:
    session = create_session(DEFAULT_MODEL_DIR / MODEL_FILENAME, 2, spinning=False)
    assert session.get_session_options().get_session_config_entry("session.intra_op.allow_spinning") == "0"


@pytest.mark.parametrize(
    ("cpu_max", "quota_cores"), [("max 100000\n", None), ("100000 100000\n", 1), ("50000 100000\n", 1)]
)
def test_usable_cores_follow_the_cgroup_quota(tmp_path: Path, cpu_max: str, quota_cores: int | None) -> None:
    affinity = len(os.sched_getaffinity(0))
    quota = tmp_path / "cpu.max"
    quota.write_text(cpu_max)
    assert usable_cores(tmp_path / "absent") == affinity
    assert usable_cores(quota) == (affinity if quota_cores is None else min(affinity, quota_cores))
