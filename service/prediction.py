"""The predict use case: image bytes and a query in, calibrated sets, guarantees and pose sets out
(``Predictor.predict``). Scores live in heatmap coordinates (scale-free across object sizes); sets
are mapped to image pixels through each instance's crop affine.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from service.calibration.registry import CalibrationRegistry, ChannelThresholds
from service.calibration.stratification import DIFFICULTY, RowAnswers, Stratum, answer_rows, parse_stratify
from service.conformal import (
    CoverageGuarantee,
    HeatmapStatistics,
    get_nonconformity_score,
    heatmap_statistics,
    map_sets_to_image,
    statistics_for,
)
from service.conformal.features import heatmap_features
from service.detector.boxes import box_problem
from service.detector.frames import EncodedFrame, ImageSource, image_source, open_frame
from service.detector.images import checked_image_header
from service.detector.manifest import HeatmapSpec
from service.detector.session import Detector, InstanceHeatmaps
from service.errors import InvalidInput
from service.monitoring.drift_monitor import DriftMonitor
from service.monitoring.looks import Frame
from service.pose import PoseOptions, PoseSets, check_pose_request, estimate_pose_sets


def _check_instances(instances: Sequence[Instance], width: int, height: int, limit: int) -> None:
    """Refuse instances the image cannot answer for, naming each problem."""
    if len(instances) > limit:
        raise InvalidInput(
            f"{len(instances)} instances in one request; the limit is {limit}: send the rest in another"
        )
    problems = [
        f"instances[{i}].bbox: {problem}"
        for i, instance in enumerate(instances)
        if (problem := box_problem(instance.bbox, width, height))
    ]
    if problems:
        raise InvalidInput("; ".join(problems[:5]), errors=problems)


@dataclass(frozen=True)
class CalibratedSets:
    """Sets of every (instance, keypoint) row of an inference result, in image pixels."""

    centers: np.ndarray  # (M, 2)
    shapes: np.ndarray  # (M, 2, 2), (y - c)^T L (y - c) <= 1; zeros = unbounded
    statistics: HeatmapStatistics
    thresholds: np.ndarray | None = None  # (M,) each row's threshold (inf: unbounded)


def calibrated_sets(
    result: InstanceHeatmaps,
    kind: str,
    channel_thresholds: np.ndarray,
    heatmap: HeatmapSpec,
    all_statistics: bool = False,
    row_thresholds: Callable[[HeatmapStatistics], np.ndarray] | None = None,
) -> CalibratedSets:
    """Apply per-channel thresholds (or ``row_thresholds``: Mondrian strata) to a detector result and
    map the sets to the image; ``all_statistics``: every heatmap statistic, not only ``kind``'s."""
    score = get_nonconformity_score(kind)
    options = (heatmap.normalization, heatmap.top_k, heatmap.temperature)
    if all_statistics:
        statistics = heatmap_statistics(result.heatmaps, *options)
    else:
        statistics = statistics_for(score, result.heatmaps, *options)
    per_row = channel_thresholds[result.channel] if row_thresholds is None else row_thresholds(statistics)
    centers, shapes = score.region(statistics, per_row)
    centers, shapes = map_sets_to_image(centers, shapes, result.affines[result.instance_index])
    return CalibratedSets(centers, shapes, statistics, per_row)


@dataclass(frozen=True)
class Instance:
    """One object to locate keypoints for: its class (one of the model's objects), its box
    ``(x, y, w, h)`` of finite numbers in image pixels and, for group strata, the caller's group."""

    object: str
    bbox: tuple[float, float, float, float]
    group: str | None = None


@dataclass(frozen=True)
class PredictQuery:
    """What one predict request asks, in domain terms (the API builds it from its schema)."""

    instances: tuple[Instance, ...]
    epsilon: float = 0.1
    nonconformity: str = "cov"
    coverage: str = "keypoint"
    delta: float | None = None
    calibration_version: int | None = None
    include_statistics: bool = False
    stratify: str | Sequence[str] = "none"  # parsed where its refusal belongs, after the model ran
    group_fallback: str = "refuse"
    pose: PoseOptions | None = None
    retain: bool = False  # kept for feedback: every heatmap statistic is computed

    @property
    def boxes(self) -> np.ndarray:
        """``(N, 4)`` ``[x, y, w, h]`` of the instances, in image pixels."""
        return np.array([instance.bbox for instance in self.instances], dtype=np.float64)


@dataclass(frozen=True)
class Prediction:
    """The calibrated sets of one request: (instance, keypoint) rows in the detector's order, each with
    its guarantee and the Mondrian stratum that answered (None: pooled); ``source``, for a drawing."""

    model_name: str
    model_hash: str
    version: int
    source: ImageSource
    sets: CalibratedSets
    channel: np.ndarray
    instance_index: np.ndarray
    guarantees: list[tuple[CoverageGuarantee, Stratum | None]]
    poses: list[PoseSets] | None
    affines: np.ndarray | None = None  # (N, 2, 3) each instance's image -> heatmap affine

    @property
    def image(self) -> np.ndarray:
        """The whole image's pixels, BGR or gray (``ValueError`` when only regions were sent)."""
        return self.source.pixels

    @property
    def width(self) -> int:
        return self.source.width

    @property
    def height(self) -> int:
        return self.source.height


@dataclass(frozen=True)
class Predictor:
    """The long-lived parts a prediction reads, and the limits it enforces (CKS_MAX_IMAGE_PIXELS,
    the decoded bytes and the instances of an image)."""

    detector: Detector
    registry: CalibrationRegistry
    drift: DriftMonitor | None
    max_image_pixels: int
    max_decoded_bytes: int
    max_instances: int

    def predict(
        self, image: bytes | EncodedFrame, query: PredictQuery, whole_image: bool = False
    ) -> Prediction:
        """Decode (``whole_image``: every pixel, for a drawing), check, pick the calibration, infer,
        calibrate the sets, record drift, estimate poses; refusals come before the model runs."""
        with self.detector.computing():  # a lone request's run takes every usable core
            manifest = self.detector.manifest
            source = self._source(image, query, whole_image)
            objects = [instance.object for instance in query.instances]
            if query.pose is not None:
                check_pose_request(manifest, objects, query.coverage, query.pose)
            version = self.registry.resolve(query.calibration_version)
            kind = query.nonconformity
            thresholds = self.registry.thresholds(version, kind, query.coverage, query.epsilon, query.delta)

            boxes = query.boxes
            result = self.detector.infer(source, boxes, objects)

            kinds = parse_stratify(query.stratify)
            strata = (
                _RequestStrata(self.registry, version, kinds, query, result, thresholds) if kinds else None
            )
            drift = self.drift
            all_statistics = query.include_statistics or (drift is not None and drift.wants_all_statistics())
            all_statistics = all_statistics or DIFFICULTY in kinds  # difficulty strata need every feature
            all_statistics = all_statistics or query.retain
            row_thresholds = strata.thresholds if strata else None
            sets = calibrated_sets(
                result, kind, thresholds.values, manifest.heatmap, all_statistics, row_thresholds
            )
            if drift is not None:
                drift.record(result.channel, sets.statistics, kind, sets.shapes, Frame(tuple(objects), boxes))
            if strata is not None:
                guarantees = strata.guarantees()
            else:
                guarantees = [(thresholds.guarantees[c], None) for c in result.channel]
            rows = (result.channel, result.instance_index)
            poses = None
            if query.pose is not None:
                poses = estimate_pose_sets(manifest, objects, query.pose, sets.centers, sets.shapes, *rows)
            model = (manifest.name, self.detector.model_hash, version)
            return Prediction(*model, source, sets, *rows, guarantees, poses, result.affines)

    def _source(self, image: bytes | EncodedFrame, query: PredictQuery, whole_image: bool) -> ImageSource:
        """The request's pixels its boxes' crops read (every pixel when ``whole_image``), checked first."""
        manifest = self.detector.manifest
        if isinstance(image, EncodedFrame):
            _check_instances(query.instances, image.width, image.height, self.max_instances)
            limits = (self.max_image_pixels, self.max_decoded_bytes)
            return open_frame(image, query.boxes, manifest.crop.padding, *limits)
        header = checked_image_header(image, self.max_image_pixels, self.max_decoded_bytes)
        _check_instances(query.instances, header.width, header.height, self.max_instances)
        return image_source(image, header, None if whole_image else query.boxes, manifest.crop.padding)


@dataclass
class _RequestStrata:
    """The Mondrian thresholds of one request's rows, chosen once their heatmap statistics exist."""

    registry: CalibrationRegistry
    version: int
    kinds: frozenset[str]
    query: PredictQuery
    result: InstanceHeatmaps
    pooled: ChannelThresholds
    _answers: RowAnswers | None = None

    def thresholds(self, statistics: HeatmapStatistics) -> np.ndarray:
        p, result, kinds = self.query, self.result, self.kinds
        stratified = self.registry.stratified(
            self.version, kinds, p.nonconformity, p.coverage, p.epsilon, p.delta
        )
        features = heatmap_features(statistics) if DIFFICULTY in kinds else None
        rows = (result.channel, result.instance_index, [p.instances[i].group for i in result.instance_index])
        pooled = (self.pooled.values, self.pooled.guarantees)
        self._answers = answer_rows(*stratified, pooled, *rows, features, p.group_fallback)
        return self._answers.values

    def guarantees(self) -> list[tuple[CoverageGuarantee, Stratum | None]]:
        assert self._answers is not None
        return list(zip(self._answers.guarantees, self._answers.strata, strict=True))
