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


def easy_and_hard(
    instance: np.ndarray, relative_area: np.ndarray, visib_fract: np.ndarray
) -> tuple[int, int]:
    """Instances for the overlays: the smallest median relative set among well visible
    instances (visib_fract >= 0.9, else the top quarter), the largest among occluded ones
    (visib_fract < 0.5, else the bottom quarter)."""
    ids, index = np.unique(instance, return_inverse=True)
    medians = np.array([np.median(relative_area[index == i]) for i in range(len(ids))])
    fraction = np.array([visib_fract[index == i][0] for i in range(len(ids))])
    easy_pool = fraction >= min(0.9, np.quantile(fraction, 0.75))
    hard_pool = fraction < max(0.5, np.quantile(fraction, 0.25))
    easy = ids[easy_pool][np.argmin(medians[easy_pool])]
    hard_candidates = hard_pool if hard_pool.any() else ~easy_pool
    hard = ids[hard_candidates][np.argmax(medians[hard_candidates])]
    return int(easy), int(hard)
