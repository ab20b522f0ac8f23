"""One predict request, from a decoded image to the response body.

Scores live in heatmap coordinates (scale-free across object sizes); sets are mapped to
image pixels through each instance's crop affine.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from service.api.pose_presenter import pose_blocks, pose_options
from service.api.schemas import (
    BallSet,
    BetaLaw,
    CalibrationRef,
    EllipseSet,
    Guarantee,
    ImageInfo,
    InstanceIn,
    InstanceOut,
    KeypointOut,
    KeypointStatistics,
    ModelRef,
    PredictParameters,
    PredictResponse,
    SignalRange,
    Stratum,
    UnboundedSet,
)
from service.calibration.registry import CalibrationRegistry, ChannelThresholds
from service.calibration.stratification import DIFFICULTY, RowAnswers, answer_rows, parse_stratify
from service.calibration.stratification import Stratum as StratumChoice
from service.conformal import (
    CoverageGuarantee,
    HeatmapStatistics,
    ellipse_axes,
    get_nonconformity_score,
    heatmap_statistics,
    map_sets_to_image,
    statistics_for,
)
from service.conformal.features import heatmap_features
from service.detector.boxes import box_problem
from service.detector.manifest import HeatmapSpec, Manifest
from service.detector.runtime import InstanceHeatmaps
from service.errors import InvalidInput
from service.state import ServiceState


def check_instances(
    instances: list[InstanceIn], manifest: Manifest, width: int, height: int, limit: int
) -> None:
    """Refuse instances the model cannot answer for, naming each problem."""
    if len(instances) > limit:
        raise InvalidInput(
            f"{len(instances)} instances in one request; the limit is {limit} (CKS_MAX_INSTANCES)"
        )
    problems = []
    known = set(manifest.object_names)
    for i, instance in enumerate(instances):
        if instance.object not in known:
            problems.append(
                f"instances[{i}].object {instance.object!r} is not an object of model {manifest.name!r} "
                f"(known: {', '.join(manifest.object_names)})"
            )
        problem = box_problem(instance.bbox, width, height)
        if problem:
            problems.append(f"instances[{i}].bbox: {problem}")
    if problems:
        raise InvalidInput("; ".join(problems[:5]), errors=problems)


@dataclass(frozen=True)
class CalibratedSets:
    """Sets of every (instance, keypoint) row of an inference result, in image pixels."""

    centers: np.ndarray  # (M, 2)
    shapes: np.ndarray  # (M, 2, 2), (y - c)^T L (y - c) <= 1; zeros = unbounded
    statistics: HeatmapStatistics


def calibrated_sets(
    result: InstanceHeatmaps,
    kind: str,
    channel_thresholds: np.ndarray,
    heatmap: HeatmapSpec,
    all_statistics: bool = False,
    row_thresholds: Callable[[HeatmapStatistics], np.ndarray] | None = None,
) -> CalibratedSets:
    """Apply per-channel thresholds to a detector result and map the sets to the image.

    ``all_statistics`` computes every heatmap statistic, not only those ``kind`` needs;
    ``row_thresholds`` (given them) picks one threshold per row instead (Mondrian strata).
    """
    score = get_nonconformity_score(kind)
    options = (heatmap.normalization, heatmap.top_k, heatmap.temperature)
    if all_statistics:
        statistics = heatmap_statistics(result.heatmaps, *options)
    else:
        statistics = statistics_for(score, result.heatmaps, *options)
    per_row = channel_thresholds[result.channel] if row_thresholds is None else row_thresholds(statistics)
    centers, shapes = score.region(statistics, per_row)
    centers, shapes = map_sets_to_image(centers, shapes, result.affines[result.instance_index])
    return CalibratedSets(centers, shapes, statistics)


def predict(state: ServiceState, image: np.ndarray, parameters: PredictParameters) -> PredictResponse:
    """Run the detector on every instance as one batch and return calibrated sets."""
    detector, registry = state.detector, state.registry
    manifest = detector.manifest
    height, width = image.shape[:2]
    check_instances(parameters.instances, manifest, width, height, state.settings.max_instances)
    pose = pose_options(parameters, manifest)
    version = registry.resolve(parameters.calibration_version)
    kind, scope = parameters.nonconformity, parameters.coverage
    thresholds = registry.thresholds(version, kind, scope, parameters.epsilon, parameters.delta)

    boxes = np.array([instance.bbox for instance in parameters.instances], dtype=np.float64)
    result = detector.infer(image, boxes, [instance.object for instance in parameters.instances])

    kinds = parse_stratify(parameters.stratify)
    strata = _RequestStrata(registry, version, kinds, parameters, result, thresholds) if kinds else None
    drift = state.drift
    all_statistics = parameters.include_statistics or (drift is not None and drift.wants_all_statistics())
    all_statistics = all_statistics or DIFFICULTY in kinds  # difficulty strata need every feature
    sets = calibrated_sets(result, kind, thresholds.values, manifest.heatmap, all_statistics,
                           strata.thresholds if strata else None)  # fmt: skip
    centers, shapes, statistics = sets.centers, sets.shapes, sets.statistics
    if drift is not None:
        drift.record(result.channel, statistics, kind, shapes)
    regions = _regions(centers, shapes, kind)
    if strata is not None:
        guarantees = strata.guarantees(scope)
    else:
        guarantees = [_guarantee(thresholds.guarantees[c], scope) for c in result.channel]
    stats = _statistics(statistics) if parameters.include_statistics else [None] * len(regions)
    poses = pose_blocks(pose, manifest, parameters, centers, shapes, result.channel, result.instance_index)
    keypoints = [
        KeypointOut(
            index=int(channel),
            name=manifest.keypoints[channel].name,
            point=(float(centers[row, 0]), float(centers[row, 1])),
            set=regions[row],
            guarantee=guarantees[row],
            statistics=stats[row],
        )
        for row, channel in enumerate(result.channel)
    ]
    instances = [
        InstanceOut(
            object=instance.object,
            bbox=instance.bbox,
            keypoints=[kp for kp, owner in zip(keypoints, result.instance_index, strict=True) if owner == i],
            pose=poses[i],
        )
        for i, instance in enumerate(parameters.instances)
    ]
    return PredictResponse(
        model=ModelRef(name=manifest.name, hash=detector.model_hash),
        calibration=CalibrationRef(
            version=version,
            nonconformity=kind,
            coverage=scope,
            epsilon=parameters.epsilon,
            delta=parameters.delta,
        ),
        image=ImageInfo(width=width, height=height),
        instances=instances,
    )


class _RequestStrata:
    """The Mondrian thresholds of one request's rows, chosen once their heatmap statistics exist."""

    def __init__(
        self,
        registry: CalibrationRegistry,
        version: int,
        kinds: frozenset[str],
        parameters: PredictParameters,
        result: InstanceHeatmaps,
        pooled: ChannelThresholds,
    ) -> None:
        self._lookup = (registry, version, kinds, parameters, result, pooled)
        self._answers: RowAnswers | None = None

    def thresholds(self, statistics: HeatmapStatistics) -> np.ndarray:
        registry, version, kinds, parameters, result, pooled = self._lookup
        p = parameters
        options = (p.nonconformity, p.coverage, p.epsilon, p.delta)
        stratified, refusal = registry.stratified(version, kinds, *options)
        features = heatmap_features(statistics) if DIFFICULTY in kinds else None
        groups = [p.instances[i].group for i in result.instance_index]
        self._answers = answer_rows(stratified, refusal, (pooled.values, pooled.guarantees), result.channel,
                                    result.instance_index, groups, features, p.group_fallback)  # fmt: skip
        return self._answers.values

    def guarantees(self, scope: str) -> list[Guarantee]:
        assert self._answers is not None
        rows = zip(self._answers.guarantees, self._answers.strata, strict=True)
        return [_guarantee(guarantee, scope, stratum) for guarantee, stratum in rows]


def _regions(centers: np.ndarray, shapes: np.ndarray, kind: str) -> list:
    semi_minor, semi_major, angles = ellipse_axes(shapes)
    regions = []
    for row, center in enumerate(centers):
        c = (float(center[0]), float(center[1]))
        a, b = float(semi_minor[row]), float(semi_major[row])
        if math.isinf(b):
            regions.append(UnboundedSet(reason="too few calibration scores for this epsilon (t = 0)"))
        elif a == b and (kind != "cov" or a == 0.0):
            regions.append(BallSet(center=c, radius=b))
        else:
            shape = shapes[row]
            regions.append(
                EllipseSet(
                    center=c,
                    shape_matrix=(
                        (float(shape[0, 0]), float(shape[0, 1])),
                        (float(shape[1, 0]), float(shape[1, 1])),
                    ),
                    semi_axes=(a, b),
                    angle_deg=float(angles[row]),
                )
            )
    return regions


def _stratum(choice: StratumChoice) -> Stratum:
    edges = [SignalRange(signal=s, low=low, high=high) for s, low, high in choice.ranges] or None
    return Stratum(kind=choice.kinds, group=choice.group, bin=choice.bin, edges=edges,
                   conditional=choice.kinds != "pooled", fallback=choice.fallback)  # fmt: skip


@lru_cache(maxsize=4096)
def _guarantee(guarantee: CoverageGuarantee, scope: str, stratum: StratumChoice | None = None) -> Guarantee:
    return Guarantee(
        scope=scope,
        n=guarantee.n,
        t=guarantee.t,
        epsilon=guarantee.epsilon,
        coverage_lower_bound=guarantee.marginal_lower,
        coverage_upper_bound=guarantee.marginal_upper,
        conditional_coverage=BetaLaw(a=guarantee.beta_a, b=guarantee.beta_b),
        delta=guarantee.delta,
        pac_failure_probability=guarantee.pac_failure_probability if guarantee.delta is not None else None,
        stratum=None if stratum is None else _stratum(stratum),
    )


def _statistics(statistics: HeatmapStatistics) -> list[KeypointStatistics]:
    covariance = statistics.covariance
    gamma = np.sqrt(statistics.variance)
    return [
        KeypointStatistics(
            peak_probability=float(statistics.peak_probability[i]),
            peak=tuple(statistics.peak_location[i]),
            mean=tuple(statistics.mean[i]),
            gamma=float(gamma[i]),
            covariance=(tuple(covariance[i, 0]), tuple(covariance[i, 1])),
        )
        for i in range(len(gamma))
    ]
