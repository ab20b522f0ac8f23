"""Calibration tables, thresholds and image-space sets for cached rows, via the service's code.

``score_table`` builds the same ``ScoreTable`` a calibration version stores, so the
thresholds are exactly ``channel_thresholds``' (the service's, for any scope, epsilon and
PAC delta). ``row_sets`` composes the same public steps as ``service.prediction.
calibrated_sets`` (``region`` of the nonconformity function, then ``map_sets_to_image``) on
cached statistics instead of raw heatmaps; ``tests/training/test_evidence.py`` checks
that both give the same sets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration_store import ObjectScores, ScoreTable
from service.calibration.registry import ChannelThresholds, channel_thresholds
from service.conformal import contains, get_nonconformity_score, map_sets_to_image
from service.detector.manifest import Manifest
from training.evidence.baseline import BASELINE_KIND
from training.evidence.inference import ALL_KINDS, SplitData


@dataclass(frozen=True)
class RowSets:
    """Sets of every row, image pixels: (y - c)^T L (y - c) <= 1, L = 0 unbounded."""

    centers: np.ndarray  # (R, 2)
    shapes: np.ndarray  # (R, 2, 2)
    covered: np.ndarray  # (R,) true keypoint inside (False for unlabeled rows)


def score_table(data: SplitData, manifest: Manifest, kinds: tuple[str, ...] = ALL_KINDS) -> ScoreTable:
    """The ScoreTable of the rows' instances, one block per object (as calibration stores it)."""
    blocks = []
    for obj in manifest.objects:
        rows = np.flatnonzero(np.isin(data.channel, obj.keypoints))
        if rows.size == 0:
            continue
        k = len(obj.keypoints)
        instances = data.instance[rows].reshape(-1, k)
        if not (data.channel[rows].reshape(-1, k) == np.asarray(obj.keypoints)).all():
            raise ValueError(f"rows of {obj.name!r} are not instance-major in manifest order")
        scores = {kind: data.scores[kind][rows].reshape(-1, k) for kind in kinds}
        refs = tuple(str(i) for i in instances[:, 0])
        blocks.append(ObjectScores(obj.name, np.asarray(obj.keypoints), refs, scores))
    return ScoreTable(tuple(blocks))


def thresholds(
    table: ScoreTable,
    manifest: Manifest,
    kind: str,
    epsilon: float,
    scope: str = "keypoint",
    delta: float | None = None,
) -> ChannelThresholds:
    """The service's per-channel thresholds for this calibration table."""
    return channel_thresholds(table, manifest.num_keypoints, kind, scope, epsilon, delta)


def row_sets(data: SplitData, kind: str, channel_values: np.ndarray) -> RowSets:
    """ICP sets of every row for per-channel thresholds, and whether they cover the label."""
    if kind == BASELINE_KIND:
        raise ValueError("the baseline's sets are pixel sets; see training.evidence.baseline")
    score = get_nonconformity_score(kind)
    centers, shapes = score.region(data.statistics(), channel_values[data.channel])
    centers, shapes = map_sets_to_image(centers, shapes, data.affine)
    labeled = data.labeled
    covered = np.zeros(len(centers), dtype=bool)
    covered[labeled] = contains(data.label[labeled], centers[labeled], shapes[labeled])
    return RowSets(centers, shapes, covered)


def covered_by_score(data: SplitData, kind: str, channel_values: np.ndarray) -> np.ndarray:
    """(R,) score <= threshold: the ICP definition of coverage (False for unlabeled rows)."""
    with np.errstate(invalid="ignore"):
        return data.scores[kind] <= channel_values[data.channel]
