"""What Theorem 1 predicts for the coverage of a labeled test batch (Yang & Pavone, after Vovk 2012).

With n calibration scores and l = floor((n+1) eps), the conditional coverage is c ~ Beta(n + 1 - l, l)
(eq. 5), so the covered count of m test instances is C ~ BetaBinomial(m, n + 1 - l, l): its central
interval is the band, P(C <= covered) the p-value (l = 0: unbounded sets, all covered).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction
from statistics import NormalDist

import numpy as np

from service.conformal import beta_cdf, conformal_rank
from service.conformal.laws import betabinomial_pmf, central_interval

#: probability of the band (two-sided, central)
BAND_LEVEL = 0.95
#: family-wise error rate of the flags (Holm's step-down over every test of an audit)
FAMILY_ALPHA = 0.05
#: a recalibration should keep the conditional coverage above 1 - eps - this, with BAND_LEVEL odds
RECALIBRATION_TOLERANCE = 0.02
_MAX_RECALIBRATION_N = 10_000_000
_NORMAL = NormalDist()


def covered_count_pmf(m: int, n: int, epsilon: float) -> np.ndarray:
    """P(C = k), k = 0..m, under a valid calibration of n scores at ``epsilon`` (all mass at m when l = 0)."""
    rank = conformal_rank(n, epsilon)
    if rank == 0:
        return np.eye(m + 1)[m]
    return betabinomial_pmf(m, n + 1 - rank, rank)


@dataclass(frozen=True)
class CoverageTest:
    """One audited figure: ``covered`` of m instances against a valid calibration of n scores at rank l."""

    m: int
    covered: int
    n: int
    rank: int  # l = floor((n+1) eps)
    epsilon: float
    band: tuple[int, int]  # covered counts: P(band[0] <= C <= band[1]) >= BAND_LEVEL
    p_value: float  # P(C <= covered): small when the coverage is lower than promised

    @property
    def coverage(self) -> float | None:
        return None if self.m == 0 else self.covered / self.m

    @property
    def in_band(self) -> bool:
        return self.band[0] <= self.covered <= self.band[1]


def coverage_test(covered: int, m: int, n: int, epsilon: float) -> CoverageTest:
    """The band and the one-sided p-value of ``covered`` out of ``m`` (Theorem 1, eq. 5)."""
    if not 0 <= covered <= m:
        raise ValueError(f"covered must be in [0, m], got {covered} of {m}")
    pmf = covered_count_pmf(m, n, epsilon)
    p_value = float(min(1.0, pmf[: covered + 1].sum()))
    return CoverageTest(
        m, covered, n, conformal_rank(n, epsilon), epsilon, central_interval(pmf, BAND_LEVEL), p_value
    )


@dataclass(frozen=True)
class PooledTest:
    """A figure pooled over several units (keypoints, objects): its band and one-sided p-value."""

    m: int
    covered: int
    expected: float  # the mean coverage promised for these units: sum w_u (1 - l_u/(n_u+1))
    sd: float
    band: tuple[float, float]  # coverage (a share): P(inside) ~ BAND_LEVEL under a valid calibration
    p_value: float  # P(coverage this low): normal approximation

    @property
    def coverage(self) -> float | None:
        return None if self.m == 0 else self.covered / self.m

    @property
    def in_band(self) -> bool:
        return self.m == 0 or self.band[0] <= self.covered / self.m <= self.band[1]


def pooled_test(tests: Sequence[CoverageTest], labeled: np.ndarray, covered: np.ndarray) -> PooledTest:
    """The pooled coverage of units ``tests`` from ``labeled`` and ``covered`` counts (image x unit),
    whatever their dependence. Two variances add up (normal approximation): the calibration's, the
    units' c_u ~ Beta(n_u+1-l_u, l_u) perfectly correlated (sd <= sum w_u sd(c_u), w_u = m_u / m), and
    the images', cluster-robust (an image's keypoints fail together) but at least the binomial spread.
    """
    m, count = int(labeled.sum()), int(covered.sum())
    if m == 0:
        return PooledTest(0, 0, 1.0, 0.0, (0.0, 1.0), 1.0)
    weights = np.array([t.m for t in tests], dtype=np.float64) / m
    a = np.array([t.n + 1 - t.rank for t in tests], dtype=np.float64)
    b = np.array([t.rank for t in tests], dtype=np.float64)
    expected = float(np.sum(weights * a / (a + b)))
    calibration_sd = float(np.sum(weights * np.sqrt(a * b / ((a + b) ** 2 * (a + b + 1)))))
    images = int(np.count_nonzero(labeled.sum(axis=1)))
    if images < 2:
        return PooledTest(m, count, expected, math.inf, (0.0, 1.0), 1.0)
    own = covered.sum(axis=0) / np.maximum(labeled.sum(axis=0), 1)
    residuals = (covered - labeled * own).sum(axis=1)
    clustered = images / (images - 1) * float(np.sum(residuals**2))
    independent = float(np.sum(weights * m * (a / (a + b)) * (b / (a + b))))
    sd = math.hypot(calibration_sd, math.sqrt(max(clustered, independent)) / m)
    half = _NORMAL.inv_cdf((1 + BAND_LEVEL) / 2) * sd
    band = (max(0.0, expected - half), min(1.0, expected + half))
    p_value = _NORMAL.cdf((count / m - expected) / sd) if sd > 0 else float(count / m < expected)
    return PooledTest(m, count, expected, sd, band, p_value)


def recalibration_size(epsilon: float) -> int:
    """The smallest n with P(Beta(n+1-l, l) < 1 - eps - tol) <= 1 - BAND_LEVEL (eq. 5)."""
    target = 1.0 - epsilon - RECALIBRATION_TOLERANCE
    floor = conformal_floor(epsilon)
    if target <= 0 or floor >= _MAX_RECALIBRATION_N:
        return floor

    def enough(n: int) -> bool:
        rank = conformal_rank(n, epsilon)
        return rank >= 1 and beta_cdf(target, n + 1 - rank, rank) <= 1.0 - BAND_LEVEL

    low = high = floor
    while not enough(high):
        low, high = high, high * 2
        if high > _MAX_RECALIBRATION_N:
            return _MAX_RECALIBRATION_N
    return low + bisect.bisect_left(range(low, high), True, key=enough)


def conformal_floor(epsilon: float) -> int:
    """The smallest n with bounded sets at ``epsilon``: floor((n+1) eps) >= 1."""
    exact = Fraction(repr(float(epsilon)))  # the decimal the caller wrote, as conformal_rank reads it
    return max(0, math.ceil(1 / exact) - 1)
