"""Image-space sets of every row for per-channel thresholds, by the steps ``predict`` takes (the
function's ``region``, then ``map_sets_to_image``); coverage is whether the true keypoint lies in the
set (``contains``). ``covered_by_score`` is the ICP definition (score <= threshold): the report says
on how many keypoints both agree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.conformal import contains, get_nonconformity_score, map_sets_to_image
from service.evaluation.rows import Rows


@dataclass(frozen=True)
class RowSets:
    """Sets of every row, image pixels: (y - c)^T L (y - c) <= 1, L = 0 unbounded."""

    centers: np.ndarray  # (R, 2)
    shapes: np.ndarray  # (R, 2, 2)
    covered: np.ndarray  # (R,) true keypoint inside (False for unlabeled rows)


def row_sets(rows: Rows, kind: str, channel_values: np.ndarray) -> RowSets:
    """ICP sets of every row for per-channel thresholds, and whether they cover the label."""
    score = get_nonconformity_score(kind)
    centers, shapes = score.region(rows.statistics, channel_values[rows.channel])
    centers, shapes = map_sets_to_image(centers, shapes, rows.affine)
    labeled = rows.labeled
    covered = np.zeros(len(centers), dtype=bool)
    covered[labeled] = contains(rows.label[labeled], centers[labeled], shapes[labeled])
    return RowSets(centers, shapes, covered)


def covered_by_score(rows: Rows, kind: str, channel_values: np.ndarray) -> np.ndarray:
    """(R,) score <= threshold: the ICP definition of coverage (False for unlabeled rows)."""
    with np.errstate(invalid="ignore"):
        return rows.scores[kind] <= channel_values[rows.channel]
