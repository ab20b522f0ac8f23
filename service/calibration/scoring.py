"""Score labeled instances with the served detector: the numbers a calibration version stores."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from calibration_store import ObjectScores, ScoreTable
from service.calibration.coco import CocoBatch, LabeledInstance, Rejection
from service.calibration.fingerprints import UNKNOWN_DIGEST, Fingerprint
from service.conformal import (
    HEATMAP_FEATURES,
    NONCONFORMITY_SCORES,
    heatmap_features,
    heatmap_statistics,
    nonconformity_scores,
)
from service.detector.crop import apply_affines
from service.detector.images import decode_image
from service.detector.session import Detector
from service.errors import ServiceError

NONCONFORMITY_KINDS = tuple(NONCONFORMITY_SCORES)


@dataclass(frozen=True)
class InstanceScores:
    """One instance's scores per function (NaN: unlabeled) and heatmap features, each ``(K,)``."""

    scores: dict[str, np.ndarray]
    features: dict[str, np.ndarray]


@dataclass
class _ObjectRows:
    keypoint_ids: tuple[int, ...]
    refs: list[str] = field(default_factory=list)
    rows: dict[str, list[np.ndarray]] = field(default_factory=lambda: {k: [] for k in NONCONFORMITY_KINDS})
    prints: list[Fingerprint] = field(default_factory=list)
    features: dict[str, list[np.ndarray]] = field(default_factory=lambda: {f: [] for f in HEATMAP_FEATURES})
    groups: list[str] = field(default_factory=list)
    missing_features: bool = False  # an appended-to version stored none: the table keeps none


_UNKNOWN = Fingerprint(UNKNOWN_DIGEST, UNKNOWN_DIGEST)


class ScoreAccumulator:
    """Collects instances by object into a ScoreTable (features only when every instance has them)."""

    def __init__(self) -> None:
        self._objects: dict[str, _ObjectRows] = {}

    def extend(self, table: ScoreTable) -> None:
        for block in table.objects:
            rows = self._rows(block.object_name, tuple(int(k) for k in block.keypoint_ids))
            rows.refs.extend(block.instance_refs)
            for kind in NONCONFORMITY_KINDS:
                rows.rows[kind].extend(block.scores[kind])
            if block.has_hashes:
                rows.prints.extend(map(Fingerprint, block.image_hashes, block.instance_hashes))
            else:
                rows.prints.extend([_UNKNOWN] * block.n_instances)
            if set(block.features) >= set(HEATMAP_FEATURES):
                for name in HEATMAP_FEATURES:
                    rows.features[name].extend(block.features[name])
            else:
                rows.missing_features = True
            rows.groups.extend(block.groups or [""] * block.n_instances)

    def add(
        self,
        object_name: str,
        keypoint_ids: tuple[int, ...],
        ref: str,
        scored: InstanceScores,
        fingerprint: Fingerprint = _UNKNOWN,
        group: str | None = None,
    ) -> None:
        rows = self._rows(object_name, keypoint_ids)
        rows.refs.append(ref)
        rows.prints.append(fingerprint)
        rows.groups.append(group or "")
        for kind in NONCONFORMITY_KINDS:
            rows.rows[kind].append(scored.scores[kind])
        for name in HEATMAP_FEATURES:
            rows.features[name].append(scored.features[name])

    def table(self) -> ScoreTable:
        return ScoreTable(tuple(_block(name, rows) for name, rows in sorted(self._objects.items())))

    def _rows(self, object_name: str, keypoint_ids: tuple[int, ...]) -> _ObjectRows:
        rows = self._objects.setdefault(object_name, _ObjectRows(keypoint_ids))
        if rows.keypoint_ids != keypoint_ids:
            raise ValueError(f"object {object_name!r}: keypoint ids changed between batches")
        return rows

    @property
    def count(self) -> int:
        return sum(len(rows.refs) for rows in self._objects.values())


def _block(name: str, rows: _ObjectRows) -> ObjectScores:
    features = {} if rows.missing_features else {f: np.vstack(rows.features[f]) for f in HEATMAP_FEATURES}
    return ObjectScores(
        object_name=name,
        keypoint_ids=np.asarray(rows.keypoint_ids),
        instance_refs=tuple(rows.refs),
        scores={kind: np.vstack(rows.rows[kind]) for kind in NONCONFORMITY_KINDS},
        image_hashes=tuple(p.image for p in rows.prints),
        instance_hashes=tuple(p.instance for p in rows.prints),
        features=features,
        groups=tuple(rows.groups) if any(rows.groups) else (),
    )


def score_image(
    detector: Detector, image_bgr: np.ndarray, instances: list[LabeledInstance]
) -> list[InstanceScores]:
    """Per instance: the scores of its keypoints per function (NaN: unlabeled) and their features."""
    boxes = np.stack([inst.bbox for inst in instances])
    result = detector.infer(image_bgr, boxes, [inst.object_name for inst in instances])
    labels = np.concatenate([inst.keypoints for inst in instances])  # same row order as result
    labels_hm = apply_affines(result.affines[result.instance_index], labels)
    spec = detector.manifest.heatmap
    options = (spec.normalization, spec.top_k, spec.temperature)
    features = heatmap_features(heatmap_statistics(result.heatmaps, *options))
    labeled = ~np.isnan(labels_hm).any(axis=1)
    per_kind = {}
    for kind in NONCONFORMITY_KINDS:
        scores = per_kind[kind] = np.full(len(labels), np.nan)
        if labeled.any():
            scores[labeled] = nonconformity_scores(
                kind, result.heatmaps[labeled], labels_hm[labeled], *options
            )
    bounds = np.cumsum([0] + [len(inst.keypoints) for inst in instances])
    spans = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    return [InstanceScores(_rows_of(per_kind, rows), _rows_of(features, rows)) for rows in spans]


def _rows_of(arrays: dict[str, np.ndarray], rows: slice) -> dict[str, np.ndarray]:
    return {name: values[rows] for name, values in arrays.items()}


def score_batch(
    batch: CocoBatch,
    batch_name: str,
    detector: Detector,
    accumulator: ScoreAccumulator,
    max_image_pixels: int,
    progress: Callable[[int], None] = lambda count: None,
    fingerprints: tuple[Fingerprint, ...] = (),
) -> list[Rejection]:
    """Score ``batch`` into ``accumulator``; an image that does not decode rejects its instances."""
    manifest = detector.manifest
    prints = dict(zip(((i.image_id, i.annotation_id) for i in batch.instances), fingerprints, strict=False))
    rejected = []
    for image_id, instances in batch.instances_by_image().items():
        record = batch.images[image_id]
        try:
            image = decode_image(record.path.read_bytes(), max_image_pixels)
        except ServiceError as error:
            reason = f"image file {record.file_name!r} was left out: {error.detail}"
            rejected.extend(Rejection(image_id, i.annotation_id, reason) for i in instances)
            progress(len(instances))
            continue
        for instance, scores in zip(instances, score_image(detector, image, instances), strict=True):
            keypoint_ids = manifest.object(instance.object_name).keypoints
            ref = f"{batch_name}:{image_id}:{instance.annotation_id}"
            fingerprint = prints.get((image_id, instance.annotation_id), _UNKNOWN)
            accumulator.add(instance.object_name, keypoint_ids, ref, scores, fingerprint, instance.group)
        progress(len(instances))
    return rejected
