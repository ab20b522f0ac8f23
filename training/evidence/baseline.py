"""The classification-style baseline the paper rejects (supplementary material).

The set is the smallest set of highest-probability heatmap pixels whose cumulative
normalized probability reaches a calibrated level (APS/LAC style). Its nonconformity
score is the mass of every pixel at least as probable as the label's pixel, so
{pixels j : score(j) <= thr} is the ICP set and ``score(label) <= thr`` is coverage.
A label outside the heatmap cannot be in any pixel set: it gets ``OUTSIDE_SCORE``
(above any mass) and is never counted as covered.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BASELINE_KIND = "mass"
OUTSIDE_SCORE = 2.0


@dataclass(frozen=True)
class MassCurves:
    """Per heatmap: s_i, the score of the i-th most probable pixel (nondecreasing in i)."""

    sorted_scores: np.ndarray  # (N, P)
    order: np.ndarray  # (N, P) flat pixel indices, most probable first

    def label_scores(self, label_pixels: np.ndarray) -> np.ndarray:
        """Scores (N,) of flat pixel indices (N,); -1 = outside the heatmap."""
        rank = np.argsort(self.order, axis=1)
        inside = label_pixels >= 0
        rows = np.arange(len(label_pixels))
        scores = np.full(len(label_pixels), OUTSIDE_SCORE)
        positions = rank[rows[inside], label_pixels[inside]]
        scores[inside] = self.sorted_scores[rows[inside], positions]
        return scores

    def areas(self, thresholds: np.ndarray) -> np.ndarray:
        """Number of pixels (N,) of the set {j : score(j) <= thr} for per-heatmap thresholds."""
        return np.count_nonzero(self.sorted_scores <= np.asarray(thresholds)[:, None], axis=1)


def mass_curves(probabilities: np.ndarray) -> MassCurves:
    """Mass curves of (N, H, W) probability maps; tied pixels share the mass of their group."""
    flat = probabilities.reshape(probabilities.shape[0], -1)
    order = np.argsort(-flat, axis=1, kind="stable")
    ordered = np.take_along_axis(flat, order, axis=1)
    cumulative = np.cumsum(ordered, axis=1)
    # a pixel's score includes every pixel tied with it: take the mass at its tie group's end
    group_end = np.ones_like(ordered, dtype=bool)
    group_end[:, :-1] = ordered[:, :-1] != ordered[:, 1:]
    end_index = np.where(group_end, np.arange(ordered.shape[1]), ordered.shape[1])
    end_index = np.minimum.accumulate(end_index[:, ::-1], axis=1)[:, ::-1]
    return MassCurves(np.take_along_axis(cumulative, end_index, axis=1), order)


def label_pixels(points_hm: np.ndarray, height: int, width: int) -> np.ndarray:
    """Flat index of the heatmap pixel holding each point (x, y); -1 outside or NaN."""
    with np.errstate(invalid="ignore"):
        columns, rows = np.floor(points_hm[:, 0]), np.floor(points_hm[:, 1])
        inside = (columns >= 0) & (columns < width) & (rows >= 0) & (rows < height)
    flat = np.where(inside, np.nan_to_num(rows) * width + np.nan_to_num(columns), -1)
    return flat.astype(np.int64)
