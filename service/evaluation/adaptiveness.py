"""Adaptiveness: do sets grow where the detector should be unsure (occlusion)?

Set area is compared between visible (COCO v = 2) and occluded (v = 1) keypoints, and
ranked against the fraction of the object that is visible (``visib_fract``) with a
Spearman correlation (average ranks for ties), both raw and relative to the box area
(object size alone also moves pixel areas).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def average_ranks(values: np.ndarray) -> np.ndarray:
    """Ranks 1..n, tied values sharing the mean of their ranks."""
    values = np.asarray(values, dtype=np.float64)
    order = np.argsort(values, kind="stable")
    ordered = values[order]
    starts = np.r_[True, ordered[1:] != ordered[:-1]]
    group = np.cumsum(starts) - 1
    first = np.flatnonzero(starts)
    last = np.r_[first[1:], values.size] - 1
    ranks = np.empty(values.size)
    ranks[order] = (first[group] + last[group]) / 2 + 1
    return ranks


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman rank correlation (Pearson correlation of average ranks); NaN pairs dropped."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    keep = ~(np.isnan(x) | np.isnan(y))
    if keep.sum() < 3:
        return float("nan")
    rx, ry = average_ranks(x[keep]), average_ranks(y[keep])
    rx, ry = rx - rx.mean(), ry - ry.mean()
    denominator = np.sqrt((rx * rx).sum() * (ry * ry).sum())
    return float((rx * ry).sum() / denominator) if denominator > 0 else float("nan")


@dataclass(frozen=True)
class Adaptiveness:
    kind: str
    median_area_visible: float
    median_area_occluded: float
    visible: int
    occluded: int
    rho_visib_fract: float  # Spearman(visib_fract, area)
    rho_visib_fract_relative: float  # Spearman(visib_fract, area / box side^2)

    @property
    def occluded_over_visible(self) -> float:
        return self.median_area_occluded / self.median_area_visible


def adaptiveness(
    kind: str, area: np.ndarray, visibility: np.ndarray, visib_fract: np.ndarray, box_side: np.ndarray
) -> Adaptiveness:
    """Area by visibility flag and its rank correlation with the visible fraction."""
    visible, occluded = area[visibility == 2], area[visibility == 1]
    relative = area / box_side**2
    return Adaptiveness(
        kind,
        float(np.median(visible)) if visible.size else float("nan"),
        float(np.median(occluded)) if occluded.size else float("nan"),
        int(visible.size),
        int(occluded.size),
        spearman(visib_fract, area),
        spearman(visib_fract, relative),
    )
