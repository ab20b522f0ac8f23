"""Turn stored calibration versions into the admin API's response bodies."""

from __future__ import annotations

import math

import numpy as np

from calibration_store import Activation, VersionInfo
from service.api.admin_schemas import (
    ActivationOut,
    SourceBatchOut,
    ThresholdRow,
    VersionDetail,
    VersionSummary,
)
from service.calibration.registry import CalibrationRegistry
from service.conformal import NONCONFORMITY_KINDS
from service.detector.manifest import Manifest

REPORTED_EPSILONS = (0.05, 0.1, 0.2)


def summarize(info: VersionInfo, active: int | None) -> VersionSummary:
    return VersionSummary(
        version=info.number,
        created_at=info.created_at,
        author=info.author,
        note=info.note,
        parent_version=info.parent_version,
        instances=info.n_instances,
        objects=dict(info.object_counts),
        source_batches=[SourceBatchOut(**b.as_dict()) for b in info.source_batches],
        active=info.number == active,
    )


def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def describe(
    info: VersionInfo, active: int | None, registry: CalibrationRegistry, manifest: Manifest
) -> VersionDetail:
    table = registry.scores(info.number)
    labeled: dict[str, int] = {}
    complete: dict[str, int] = {}
    for block in table.objects:
        matrix = block.scores[NONCONFORMITY_KINDS[0]]
        for column, channel in enumerate(block.keypoint_ids):
            labeled[manifest.keypoints[int(channel)].name] = int(
                np.count_nonzero(~np.isnan(matrix[:, column]))
            )
        complete[block.object_name] = int(np.count_nonzero(~np.isnan(matrix).any(axis=1)))
    rows = []
    for kind in NONCONFORMITY_KINDS:
        for epsilon in REPORTED_EPSILONS:
            per_keypoint = registry.thresholds(info.number, kind, "keypoint", epsilon, None).values
            per_object = registry.thresholds(info.number, kind, "object", epsilon, None).values
            rows.append(
                ThresholdRow(
                    nonconformity=kind,
                    epsilon=epsilon,
                    keypoint={k.name: _finite_or_none(per_keypoint[k.index]) for k in manifest.keypoints},
                    object={o.name: _finite_or_none(per_object[o.keypoints[0]]) for o in manifest.objects},
                )
            )
    return VersionDetail(
        **summarize(info, active).model_dump(),
        normalization=dict(info.normalization),
        labeled_per_keypoint=labeled,
        complete_per_object=complete,
        thresholds=rows,
    )


def activation_out(entry: Activation) -> ActivationOut:
    return ActivationOut(
        seq=entry.seq,
        version=entry.version,
        activated_at=entry.activated_at,
        who=entry.who,
        reason=entry.reason,
    )
