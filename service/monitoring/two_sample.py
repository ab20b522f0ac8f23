"""Two-sample tests of a live window against a reference sample, in numpy (no scipy at run time).

- Kolmogorov-Smirnov: D = sup |F_ref - F_live|, its p-value exact for small samples (Hodges 1958),
  else Kolmogorov's limit law with Stephens' correction (1970). No ties assumed.
- Population stability index: sum_b (live_b - ref_b) ln(live_b / ref_b) over reference quantile bins.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

#: n * m up to which the p-value is exact (a few ms); beyond, the asymptotic law is accurate
EXACT_LIMIT = 10_000
PSI_BINS = 10
_PSI_FLOOR = 1e-4  # share given to an empty bin, so ln() stays finite


def ks_statistic(reference_sorted: np.ndarray, live: np.ndarray) -> float:
    """D = sup |F_ref - F_live| (``reference_sorted`` ascending; ``live`` in any order)."""
    live_sorted = np.sort(live)
    points = np.concatenate([reference_sorted, live_sorted])
    cdf_reference = np.searchsorted(reference_sorted, points, side="right") / reference_sorted.size
    cdf_live = np.searchsorted(live_sorted, points, side="right") / live_sorted.size
    return float(np.max(np.abs(cdf_reference - cdf_live)))


def ks_p_value(statistic: float, n: int, m: int) -> float:
    """Two-sided P(D >= statistic) for samples of sizes n and m drawn from one law."""
    if n < 1 or m < 1:
        raise ValueError(f"both samples need at least one value, got n={n}, m={m}")
    if n * m <= EXACT_LIMIT:
        # D is a multiple of 1/(n m): its numerator is an integer, the cache key
        return _exact_p_value(round(statistic * n * m), min(n, m), max(n, m))
    return ks_asymptotic_p_value(statistic, n, m)


def ks_asymptotic_p_value(statistic: float, n: int, m: int) -> float:
    """Kolmogorov's limit law at lambda = (sqrt(e) + 0.12 + 0.11 / sqrt(e)) D, e = n m / (n + m)."""
    root = math.sqrt(n * m / (n + m))
    return kolmogorov_sf((root + 0.12 + 0.11 / root) * statistic)


def kolmogorov_sf(x: float) -> float:
    """P(K > x) of the Kolmogorov distribution (scipy.stats.kstwobign.sf)."""
    if x <= 0:
        return 1.0
    k = np.arange(1, 101, dtype=np.float64)
    if x < 1.0:  # the theta-function form converges fast for small x
        terms = np.exp(-((2 * k - 1) ** 2) * math.pi**2 / (8 * x * x))
        cdf = math.sqrt(2 * math.pi) / x * float(np.sum(terms))
        return float(min(max(1.0 - cdf, 0.0), 1.0))
    signs = np.where(k % 2 == 1, 1.0, -1.0)
    return float(min(max(2.0 * np.sum(signs * np.exp(-2.0 * k * k * x * x)), 0.0), 1.0))


@lru_cache(maxsize=4096)
def _exact_p_value(numerator: int, n: int, m: int) -> float:
    """1 - P(every lattice point (i, j) of a random path to (n, m) has |i m - j n| < numerator), row by
    row: u(i, j) = u(i-1, j) i / (i + j) + u(i, j-1) j / (i + j) (paths inside / C(i + j, i)) is first
    order on the row's inside interval, solved with cumulative sums and products (in logs)."""
    if numerator <= 0:
        return 1.0
    j = np.arange(m + 1, dtype=np.float64)
    row = (j * n < numerator).astype(np.float64)  # i = 0: the first cells of the row, reached from the left
    for i in range(1, n + 1):
        inside = np.flatnonzero(np.abs(i * m - j * n) < numerator)
        lo, hi = int(inside[0]), int(inside[-1]) + 1
        t = j[lo:hi]
        log_q = np.concatenate(([0.0], np.cumsum(np.log(t[1:] / (i + t[1:])))))
        carried = np.cumsum(i / (i + t) * row[lo:hi] * np.exp(-log_q))
        row = np.zeros(m + 1)
        row[lo:hi] = np.exp(log_q) * carried
    return float(min(max(1.0 - row[m], 0.0), 1.0))


def quantile_bin_edges(reference: np.ndarray, bins: int = PSI_BINS) -> np.ndarray:
    """Inner edges (bins - 1) splitting the reference into equal shares."""
    return np.quantile(reference, np.arange(1, bins) / bins)


def population_stability_index(reference: np.ndarray, live: np.ndarray, edges: np.ndarray) -> float:
    """PSI of ``live`` against ``reference`` over the bins cut at ``edges`` (quantile_bin_edges)."""
    bins = edges.size + 1
    reference_share = np.bincount(np.searchsorted(edges, reference, side="right"), minlength=bins)
    live_share = np.bincount(np.searchsorted(edges, live, side="right"), minlength=bins)
    reference_share = np.maximum(reference_share / reference.size, _PSI_FLOOR)
    live_share = np.maximum(live_share / live.size, _PSI_FLOOR)
    return float(np.sum((live_share - reference_share) * np.log(live_share / reference_share)))
