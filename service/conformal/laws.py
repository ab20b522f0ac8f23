"""Exact laws of conformal coverage: given its calibration set an ICP set's coverage is Beta(n+1-t, t)
(Theorem 1), so the points covered among m test points follow BetaBinomial(m, n+1-t, t).
Quantiles bisect the exact ``beta_cdf`` (no scipy).
"""

from __future__ import annotations

import math

import numpy as np

from .guarantees import beta_cdf


def beta_quantile(q: float, a: int, b: int, tolerance: float = 1e-10) -> float:
    """x with P(Beta(a, b) <= x) = q, by bisection on the exact CDF."""
    low, high = 0.0, 1.0
    while high - low > tolerance:
        middle = (low + high) / 2
        if beta_cdf(middle, a, b) < q:
            low = middle
        else:
            high = middle
    return (low + high) / 2


def beta_interval(a: int, b: int, level: float = 0.95) -> tuple[float, float]:
    """Central ``level`` interval of Beta(a, b)."""
    tail = (1 - level) / 2
    return beta_quantile(tail, a, b), beta_quantile(1 - tail, a, b)


def beta_pdf(x: np.ndarray, a: int, b: int) -> np.ndarray:
    """Density of Beta(a, b) on ``x`` in (0, 1)."""
    x = np.clip(np.asarray(x, dtype=np.float64), 1e-300, 1 - 1e-16)
    log_norm = math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b)
    return np.exp(log_norm + (a - 1) * np.log(x) + (b - 1) * np.log1p(-x))


def betabinomial_pmf(m: int, a: float, b: float) -> np.ndarray:
    """P(K = k), k = 0..m, for K ~ BetaBinomial(m, a, b), by the pmf's ratio recursion."""
    k = np.arange(m, dtype=np.float64)
    log_ratio = np.log(m - k) - np.log(k + 1) + np.log(k + a) - np.log(m - k - 1 + b)
    log_pmf = np.concatenate([[0.0], np.cumsum(log_ratio)])
    pmf = np.exp(log_pmf - log_pmf.max())
    return pmf / pmf.sum()


def central_interval(pmf: np.ndarray, level: float = 0.95) -> tuple[int, int]:
    """Smallest lo, hi with P(K < lo) <= tail and P(K > hi) <= tail (tail = (1-level)/2)."""
    tail = (1 - level) / 2
    cdf = np.cumsum(pmf)
    low = int(np.searchsorted(cdf, tail, side="right"))
    high = int(np.searchsorted(cdf, 1 - tail - 1e-12, side="left"))
    return low, min(high, len(pmf) - 1)
