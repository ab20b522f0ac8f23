"""The stable entry points: scores for calibration, sets for prediction."""

from __future__ import annotations

import numpy as np

from .normalization import as_raw_batch
from .scores import NonconformityScore, get_nonconformity_score
from .statistics import DEFAULT_TOP_K, HeatmapStatistics, heatmap_statistics


def statistics_for(
    score: NonconformityScore,
    heatmaps: np.ndarray,
    normalization: str = "anchor",
    top_k: int = DEFAULT_TOP_K,
    temperature: float = 1.0,
) -> HeatmapStatistics:
    """Only the statistics ``score`` needs (the peak alone skips the top-K selection)."""
    needs = {"include_peak": score.needs_peak, "include_spread": score.needs_spread}
    return heatmap_statistics(heatmaps, normalization, top_k, temperature, **needs)


def nonconformity_scores(
    kind: str,
    heatmaps: np.ndarray,
    keypoints: np.ndarray,
    normalization: str = "anchor",
    top_k: int = DEFAULT_TOP_K,
    temperature: float = 1.0,
) -> np.ndarray:
    """Scores (N,) float64 of keypoints (N, 2) (x, y heatmap coords; NaN: unlabeled, NaN score)
    under heatmaps (N, H, W)."""
    heatmaps = as_raw_batch(heatmaps)
    keypoints = np.asarray(keypoints, dtype=np.float64)
    if keypoints.shape != (heatmaps.shape[0], 2):
        raise ValueError(f"keypoints must have shape ({heatmaps.shape[0]}, 2), got {keypoints.shape}")
    score = get_nonconformity_score(kind)
    statistics = statistics_for(score, heatmaps, normalization, top_k, temperature)
    return score.score(statistics, keypoints)


def prediction_sets(
    kind: str,
    heatmaps: np.ndarray,
    threshold: float | np.ndarray,
    normalization: str = "anchor",
    top_k: int = DEFAULT_TOP_K,
    temperature: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """ICP sets (eq. 3): centres (N, 2) and shapes L (N, 2, 2), (y-c)^T L (y-c) <= 1, for one
    threshold or one per heatmap (``math.inf``, unbounded: L = 0)."""
    heatmaps = as_raw_batch(heatmaps)
    thresholds = np.asarray(threshold, dtype=np.float64)
    if thresholds.ndim == 0:
        thresholds = np.full(heatmaps.shape[0], float(thresholds))
    if thresholds.shape != (heatmaps.shape[0],):
        raise ValueError(f"threshold must be a float or an array of shape ({heatmaps.shape[0]},)")
    if np.any(np.isnan(thresholds) | (thresholds < 0)):
        raise ValueError("thresholds must be >= 0 (math.inf for an unbounded set)")
    score = get_nonconformity_score(kind)
    statistics = statistics_for(score, heatmaps, normalization, top_k, temperature)
    return score.region(statistics, thresholds)


def point_estimates(
    kind: str,
    heatmaps: np.ndarray,
    normalization: str = "anchor",
    top_k: int = DEFAULT_TOP_K,
    temperature: float = 1.0,
) -> np.ndarray:
    """Point estimates (N, 2): argmax centre for peak, top-K weighted mean for var/cov."""
    score = get_nonconformity_score(kind)
    statistics = statistics_for(score, heatmaps, normalization, top_k, temperature)
    return score.point_estimate(statistics)
