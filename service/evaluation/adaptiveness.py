"""Adaptiveness: do sets grow where the detector should be unsure (occlusion)? Set area of visible
(COCO v = 2) against occluded (v = 1) keypoints, and its Spearman correlation (average ranks for
ties) with the object's visible fraction, raw and relative to the box area (size alone moves areas)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def average_ranks(values: np.ndarray) -> np.ndarray:
    """Ranks 1..n, tied values sharing the mean of their ranks."""
    _, group, counts = np.unique(np.asarray(values, float), return_inverse=True, return_counts=True)
    return (np.cumsum(counts) - (counts - 1) / 2)[group]


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
    area: np.ndarray, visibility: np.ndarray, visib_fract: np.ndarray, box_side: np.ndarray
) -> Adaptiveness:
    """Area by visibility flag and its rank correlation with the visible fraction."""
    visible, occluded = area[visibility == 2], area[visibility == 1]
    medians = [float(np.median(a)) if a.size else float("nan") for a in (visible, occluded)]
    rho = spearman(visib_fract, area), spearman(visib_fract, area / box_side**2)
    return Adaptiveness(medians[0], medians[1], int(visible.size), int(occluded.size), *rho)
