"""The ICP threshold of eq. (3): alpha_(t), t = floor((n+1) eps), scores sorted nonincreasingly.

t = 0: the set is the whole plane, threshold ``math.inf`` (the reference code indexes alpha_(-1)
there). NaN scores are unlabeled keypoints, left out of n; +inf scores are kept.
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np


def conformal_rank(n: int, epsilon: float) -> int:
    """t = floor((n + 1) * epsilon), exact for the decimal the caller wrote (in floating point,
    100 * 0.29 = 28.999999999999996)."""
    _check_epsilon(epsilon)
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    return math.floor((n + 1) * Fraction(repr(float(epsilon))))


def threshold_for_rank(scores: np.ndarray, t: int) -> float:
    """alpha_(t), the t-th largest non-NaN score; ``math.inf`` when t == 0."""
    finite = _labeled(scores)
    if not 0 <= t <= finite.size:
        raise ValueError(f"rank t={t} outside [0, {finite.size}]")
    if t == 0:
        return math.inf
    return float(-np.partition(-finite, t - 1)[t - 1])


def conformal_threshold(scores: np.ndarray, epsilon: float) -> float:
    """The ICP threshold alpha_(floor((n+1) eps)) of eq. (3); ``math.inf`` if unbounded."""
    finite = _labeled(scores)
    return threshold_for_rank(finite, conformal_rank(finite.size, epsilon))


def labeled_counts(score_matrix: np.ndarray) -> np.ndarray:
    """n per column: the number of non-NaN scores in each column of (n_instances, n_groups)."""
    return np.count_nonzero(~np.isnan(_as_matrix(score_matrix)), axis=0)


def column_thresholds(score_matrix: np.ndarray, ranks: np.ndarray) -> np.ndarray:
    """alpha_(t_g) for every column g of (n_instances, n_groups), NaNs ignored; t_g = 0 -> inf."""
    matrix = _as_matrix(score_matrix)
    ranks = np.asarray(ranks, dtype=np.intp)
    counts = labeled_counts(matrix)
    if ranks.shape != counts.shape or np.any((ranks < 0) | (ranks > counts)):
        raise ValueError("ranks must be one integer in [0, n_g] per column")
    if matrix.shape[0] == 0:  # no row to pick from; every rank is 0
        return np.full(matrix.shape[1], np.inf)
    descending = -np.sort(-matrix, axis=0)  # NaNs sort last
    picked = descending[np.maximum(ranks - 1, 0), np.arange(matrix.shape[1])]
    return np.where(ranks == 0, np.inf, picked)


def object_scores(keypoint_scores: np.ndarray) -> np.ndarray:
    """Object-scope scores: max over an instance's keypoints (NaN unless all are labeled), so one
    threshold covers all keypoints of an object simultaneously."""
    return np.max(_as_matrix(keypoint_scores), axis=1)


def _check_epsilon(epsilon: float) -> None:
    if not 0 < epsilon < 1:
        raise ValueError(f"epsilon must be in (0, 1), got {epsilon}")


def _labeled(scores: np.ndarray) -> np.ndarray:
    scores = np.asarray(scores, dtype=np.float64).ravel()
    return scores[~np.isnan(scores)]


def _as_matrix(values: np.ndarray) -> np.ndarray:
    matrix = np.asarray(values, dtype=np.float64)
    if matrix.ndim != 2:
        raise ValueError(f"expected a 2-D (n_instances, n_groups) array, got shape {matrix.shape}")
    return matrix
