"""Recalibration from the field: labelled feedback becomes a calibration version without a zip, under
an upload's rules (repeats, equal versions, guardrails, activation floor, audit trail).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration_store import RetainedPrediction, ScoreTable, SourceBatch
from service.calibration.fingerprints import Fingerprint, instance_digest, instance_digests, stored_digests
from service.calibration.intake import (
    Parent,
    UploadOptions,
    batch_name,
    equal_version,
    read_parent,
    repeats_refused,
)
from service.calibration.scoring import NONCONFORMITY_KINDS, InstanceScores, ScoreAccumulator
from service.calibration.versions import (
    CalibrationOutcome,
    ScoredInstances,
    VersionRules,
    store_scored_version,
)
from service.conformal import heatmap_features
from service.detector.session import Detector
from service.errors import InvalidInput
from service.feedback.labels import kept_statistics
from service.infra.audit_trail import AuditTrail, Operator


@dataclass(frozen=True)
class FieldSelection:
    """Which labelled predictions become the version: all, or one stream's, or one version's answers."""

    stream: str | None = None
    served_by: int | None = None

    def __call__(self, prediction: RetainedPrediction) -> bool:
        in_stream = self.stream is None or prediction.stream == self.stream
        return in_stream and (self.served_by is None or prediction.version == self.served_by)


@dataclass(frozen=True)
class FieldInstance:
    ref: str
    object_name: str
    scores: InstanceScores
    fingerprint: Fingerprint
    group: str | None


def calibrate_from_feedback(
    store: Any,
    detector: Detector,
    scores: Callable[[int], ScoreTable],
    selection: FieldSelection,
    options: UploadOptions,
    operator: Operator,
    rules: VersionRules,
    audit: AuditTrail,
    limit: int,
) -> CalibrationOutcome:
    labelled = [p for p in store.labelled_predictions(detector.model_hash, limit) if selection(p)]
    instances = [instance for prediction in labelled for instance in field_instances(prediction)]
    if not instances:
        raise InvalidInput("no labelled feedback matches (stream, served_by): nothing to calibrate with")
    parent = None if options.append_to is None else read_parent(store, detector, options.append_to, scores)
    repeats = find_field_repeats(instances, parent)
    if repeats and not options.dedupe:
        raise repeats_refused(repeats, len(instances))
    repeated = {r.ref for r in repeats}
    kept = [instance for instance in instances if instance.ref not in repeated]
    if not kept:
        raise InvalidInput("no labelled instance is left to calibrate with once repeats are dropped")
    source = _source(kept, options.name)
    digests = {i.fingerprint.instance for i in kept}
    if parent is not None:
        digests |= instance_digests(parent.scores)
    count = len(kept) + (parent.scores.n_instances if parent is not None else 0)
    equal_version(store, detector, scores, digests, count, options)
    scored = _scored(detector, kept, parent, source)
    return store_scored_version(store, detector, scored, len(repeats), options, operator, rules, audit)


def field_instances(prediction: RetainedPrediction) -> Iterator[FieldInstance]:
    """Each labelled instance of a prediction, scored as an upload of its image and labels would be."""
    record, labels = prediction.record, prediction.labels or {}
    judged = {row["row"]: row["scores"] for row in labels.get("rows", [])}
    image = record["image"]["sha256"]
    for given in labels.get("instances", []):
        index = given["instance"]
        rows = [r for r, row in enumerate(record["rows"]) if row["instance"] == index]
        if not any(r in judged for r in rows):
            continue
        points = np.array(
            [[x, y] if v else [np.nan, np.nan] for x, y, v in given["keypoints"]], dtype=np.float64
        )
        scores = {
            kind: np.array([judged[r][kind] if r in judged else np.nan for r in rows])
            for kind in NONCONFORMITY_KINDS
        }
        features = heatmap_features(kept_statistics(record, [record["rows"][r] for r in rows]))
        instance = record["instances"][index]
        digest = instance_digest(image, instance["object"], instance["bbox"], points)
        yield FieldInstance(
            f"feedback:{prediction.id}:{index}",
            instance["object"],
            InstanceScores(scores, features),
            Fingerprint(image, digest),
            instance["group"],
        )


def find_field_repeats(instances: list[FieldInstance], parent: Parent | None) -> list[FieldRepeat]:
    """Instances already in the version appended to, or earlier in the selection."""
    old_images, old_instances = stored_digests(None if parent is None else parent.scores)
    where = f"version {parent.info.number}" if parent is not None else ""
    first_prediction: dict[str, str] = {}
    seen: set[str] = set()
    repeats = []
    for instance in instances:
        prediction = instance.ref.rsplit(":", 1)[0]
        first = first_prediction.setdefault(instance.fingerprint.image, prediction)
        reason = None
        if instance.fingerprint.image in old_images:
            reason = f"its image is already in {where}"
        elif instance.fingerprint.instance in old_instances:
            reason = f"the same instance is already in {where}"
        elif first != prediction:
            reason = f"its image was labelled already under {first}"
        elif instance.fingerprint.instance in seen:
            reason = "the same instance (image, object, box, labels) is labelled twice"
        seen.add(instance.fingerprint.instance)
        if reason:
            repeats.append(FieldRepeat(instance.ref, reason))
    return repeats


@dataclass(frozen=True)
class FieldRepeat:
    """A repeat among labelled instances, described as an upload's rejections are."""

    ref: str
    reason: str

    def describe(self) -> str:
        return f"{self.ref}: {self.reason}"


def _source(instances: list[FieldInstance], name: str | None) -> SourceBatch:
    """The selection as a source batch: its sha256 hashes the instances' refs and fingerprints."""
    text = "\n".join(f"{i.ref} {i.fingerprint.instance}" for i in instances)
    digest = hashlib.sha256(text.encode()).hexdigest()
    named = f"feedback-{digest[:12]}" if name is None else batch_name(name, digest)
    return SourceBatch(named, digest, len(instances))


def _scored(
    detector: Detector, instances: list[FieldInstance], parent: Parent | None, source: SourceBatch
) -> ScoredInstances:
    accumulator = ScoreAccumulator()
    sources = []
    if parent is not None:
        accumulator.extend(parent.scores)
        sources.extend(parent.info.source_batches)
    for i in instances:
        keypoint_ids = detector.manifest.object(i.object_name).keypoints
        accumulator.add(i.object_name, keypoint_ids, i.ref, i.scores, i.fingerprint, i.group)
    return ScoredInstances(accumulator, [*sources, source], [], len(instances))
