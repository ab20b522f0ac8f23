"""Where the time of one predict request goes, timed in-process on the functions the route calls,
and what that makes the most a server could do (``in_process_limits``).

Stages, in the route's order: ``decode_image`` -> ``build_batch`` (crop + normalize) ->
``Detector.run`` (inference) -> ``calibrated_sets`` (heatmap statistics and
sets) -> the rest of ``predict`` (checks, thresholds lookup; timed with the two previous
stages' results cached) -> the response body (``predict_json``: the response models and their
JSON), as the route writes them. Each iteration runs every stage once,
so the stages are measured side by side; the figures are medians over iterations.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks.harness import Sample
from service import prediction
from service.api.predict.predict_input import predict_query
from service.api.predict.predict_presenter import predict_json
from service.api.predict.predict_schemas import PredictParameters
from service.detector.frames import ImageSource, image_source
from service.detector.images import checked_image_header
from service.detector.preprocess import build_batch
from service.detector.session import Detector, InstanceHeatmaps
from service.infra.settings import Settings
from service.prediction import CalibratedSets, calibrated_sets
from service.serving.container import ServiceState, build_state

STAGES = ("decode", "crop", "inference", "sets", "response", "json")


@contextmanager
def service_state(model_dir: Path, inference_threads: int) -> Iterator[ServiceState]:
    """The service's own state (model, store with the bundled calibration)."""
    with tempfile.TemporaryDirectory(prefix="cks-bench-state-") as data_dir:
        settings = Settings(
            model_dir=model_dir,
            data_dir=Path(data_dir),
            inference_threads=inference_threads,
        )
        state = build_state(settings)
        try:
            yield state
        finally:
            state.close()


def _heatmaps(
    state: ServiceState, batch_out: np.ndarray, sample: Sample, affines: np.ndarray
) -> InstanceHeatmaps:
    """The rows ``Detector.infer`` keeps: each instance's own keypoint channels."""
    manifest = state.detector.manifest
    channels = [np.asarray(manifest.object(name).keypoints) for name in sample.objects]
    index = np.concatenate([np.full(len(c), i) for i, c in enumerate(channels)])
    channel = np.concatenate(channels)
    return InstanceHeatmaps(batch_out[index, channel], index, channel, affines)


def _timed(action: Callable[[], object]) -> tuple[float, object]:
    start = time.perf_counter()
    value = action()
    return (time.perf_counter() - start) * 1e3, value


@contextmanager
def _cached(
    detector: Detector, image: ImageSource, result: InstanceHeatmaps, sets: CalibratedSets
) -> Iterator[None]:
    """``image_source``, ``detector.infer`` and ``calibrated_sets`` return these at once:
    ``predict`` times the rest."""
    detector.infer = lambda image, boxes, objects: result  # type: ignore[method-assign]
    originals = prediction.calibrated_sets, prediction.image_source
    prediction.calibrated_sets = lambda *args, **kwargs: sets
    prediction.image_source = lambda *args, **kwargs: image
    try:
        yield
    finally:
        del detector.infer
        prediction.calibrated_sets, prediction.image_source = originals


def _one_iteration(state: ServiceState, sample: Sample, parameters: PredictParameters) -> dict[str, float]:
    manifest, detector, registry = state.detector.manifest, state.detector, state.registry
    limit = state.settings.predict.max_image_pixels
    ms: dict[str, float] = {}
    header = checked_image_header(sample.jpeg, limit)
    padding = manifest.crop.padding
    ms["decode"], image = _timed(lambda: image_source(sample.jpeg, header, sample.boxes, padding))
    ms["crop"], (batch, affines) = _timed(lambda: build_batch(image, sample.boxes, manifest))
    ms["inference"], out = _timed(lambda: detector.run(batch))
    result = _heatmaps(state, out, sample, affines)
    version = registry.resolve(parameters.calibration_version)
    thresholds = registry.thresholds(
        version, parameters.nonconformity, parameters.coverage, parameters.epsilon, parameters.delta
    )
    ms["sets"], sets = _timed(
        lambda: calibrated_sets(result, parameters.nonconformity, thresholds.values, manifest.heatmap)
    )
    query = predict_query(parameters)
    with _cached(detector, image, result, sets):
        ms["response"], answer = _timed(lambda: state.predictor.predict(sample.jpeg, query))
    ms["json"], _ = _timed(lambda: predict_json(answer, query, manifest))
    return ms


def stage_breakdown(state: ServiceState, sample: Sample, iterations: int) -> dict[str, float]:
    """Median milliseconds per stage (and their sum as ``total``) for one request of ``sample``."""
    parameters = PredictParameters.model_validate_json(sample.parameters_json())
    _one_iteration(state, sample, parameters)  # warm-up
    runs = [_one_iteration(state, sample, parameters) for _ in range(iterations)]
    medians = {stage: statistics.median(run[stage] for run in runs) for stage in STAGES}
    medians["total"] = sum(medians.values())
    return medians


@dataclass(frozen=True)
class Limit:
    """The in-process limit: core-ms per request is the process's CPU time per request while the
    breakdown runs with one intra-op thread (CPU, not wall time: other jobs on the machine do not
    inflate it), so many clients get at most cores / core-ms; one client at best the smallest
    wall-clock total over the thread settings (one intra-op thread, or one per core)."""

    boxes: int
    core_ms: float  # CPU time per request, one intra-op thread
    best_latency_ms: float  # smallest total over the thread settings
    best_threads: int
    stages: dict[str, float]  # one intra-op thread

    @property
    def requests_per_s(self) -> float:
        return cores() * 1e3 / self.core_ms


def cores() -> int:
    return len(os.sched_getaffinity(0))


def in_process_limits(
    model_dir: Path, sample: Sample, boxes: tuple[int, ...], iterations: int
) -> list[Limit]:
    """One ``Limit`` per box count, the stages timed with one intra-op thread and with one per core."""
    totals: dict[int, dict[int, dict[str, float]]] = {}
    core_ms: dict[int, float] = {}
    for threads in sorted({1, cores()}):
        with service_state(model_dir, threads) as state:
            totals[threads] = {}
            for n in boxes:
                started = time.process_time()
                totals[threads][n] = stage_breakdown(state, sample.with_instances(n), iterations)
                if threads == 1:  # iterations plus the warm-up
                    core_ms[n] = (time.process_time() - started) * 1e3 / (iterations + 1)
    limits = []
    for n in boxes:
        best = min(totals, key=lambda t: totals[t][n]["total"])
        limits.append(Limit(n, core_ms[n], totals[best][n]["total"], best, totals[1][n]))
    return limits
