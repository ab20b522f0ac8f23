"""The benchmarks that need no server: post-processing, calibration scoring, store writes."""

from __future__ import annotations

import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks import bench_conformal, bench_store
from service.calibration.coco import load_coco_batch
from service.calibration.scoring import ScoreAccumulator, score_batch
from service.conformal import nonconformity_scores
from service.detector.session import Detector


@dataclass(frozen=True)
class PostProcessing:
    kind: str
    loop_us: float  # per heatmap, the straightforward per-heatmap loop
    vectorized_us: float  # per heatmap, service.conformal

    @property
    def speedup(self) -> float:
        return self.loop_us / self.vectorized_us


def post_processing(quick: bool) -> list[PostProcessing]:
    """bench_conformal's batch (76 float32 heatmaps 64x64, as its default): loop vs vectorized."""
    exact, keypoints = bench_conformal.make_batch()
    heatmaps = exact.astype(np.float32)  # the detector's output dtype
    pairs = list(zip(heatmaps, keypoints, strict=True))
    loop_repeats, vector_repeats = (1, 5) if quick else (3, 20)
    results = []
    for kind in ("peak", "var", "cov"):
        loop_us = bench_conformal.per_heatmap_us(
            lambda kind=kind: [bench_conformal.loop_score(kind, h, k) for h, k in pairs], loop_repeats
        )
        vector_us = bench_conformal.per_heatmap_us(
            lambda kind=kind: nonconformity_scores(kind, heatmaps, keypoints, top_k=bench_conformal.TOP_K),
            vector_repeats,
        )
        results.append(PostProcessing(kind, loop_us, vector_us))
    return results


@dataclass(frozen=True)
class Calibration:
    instances: int
    seconds: float
    store_write_best_s: float
    store_write_median_s: float
    store_instances: int

    @property
    def instances_per_s(self) -> float:
        return self.instances / self.seconds


def calibration_scoring(samples_dir: Path, model_dir: Path, threads: int) -> tuple[int, float]:
    """``(instances, seconds)`` to score the COCO samples folder as ``keypoint-service calibrate`` does."""
    detector = Detector(model_dir, threads)
    batch = load_coco_batch(samples_dir, detector.manifest)
    start = time.perf_counter()
    score_batch(batch, "samples", detector, ScoreAccumulator(), max_image_pixels=10**9)
    return batch.count, time.perf_counter() - start


def store_write(instances: int, repeat: int) -> list[float]:
    """Seconds to write one version of ``instances`` instances to SQLite (bench_store)."""
    table = bench_store.build_table(instances)
    with tempfile.TemporaryDirectory(prefix="cks-bench-store-") as directory:
        return bench_store.bench(f"sqlite://{directory}/bench.db", table, repeat)["write"]


def calibration(samples_dir: Path, model_dir: Path, threads: int, quick: bool) -> Calibration:
    count, seconds = calibration_scoring(samples_dir, model_dir, threads)
    writes = store_write(100_000, 1 if quick else 3)
    return Calibration(count, seconds, min(writes), statistics.median(writes), 100_000)
