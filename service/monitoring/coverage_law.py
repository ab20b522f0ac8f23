"""What Theorem 1 predicts for the empirical coverage of a labeled test batch, and how to
tell a calibration that no longer holds from bad luck.

Yang & Pavone, "Conformal Semantic Keypoint Detection with Statistical Guarantees",
Theorem 1 (after Vovk 2012, "Conditional validity of inductive conformal predictors"):
with n calibration scores and rank l = floor((n+1) eps), the coverage of the sets
*conditional on the calibration set* is a random variable

    c ~ Beta(n + 1 - l, l)                                          (eq. 5)

over the draws of calibration sets. A batch of m new instances, exchangeable with the
calibration ones, is covered c·m times on average and, given c, the covered count is
Binomial(m, c). Unconditionally the covered count is the mixture

    C ~ BetaBinomial(m, n + 1 - l, l),

whose central 95% interval is the band an audit's coverage falls in when the calibration
is valid, and whose lower tail P(C <= covered) is the p-value of "the coverage is below
what the calibration promises". l = 0 (n + 1 < 1/eps) means unbounded sets: everything
is covered.

Pure numpy and ``math``: scipy is not a runtime dependency (its ``stats.betabinom`` is
what the tests compare with).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction

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


def covered_count_pmf(m: int, n: int, epsilon: float) -> np.ndarray:
    """P(C = k), k = 0..m: the covered count of m test instances under a valid calibration of
    n scores at ``epsilon`` (BetaBinomial(m, n+1-l, l); all mass at m when l = 0)."""
    rank = conformal_rank(n, epsilon)
    if rank == 0:
        pmf = np.zeros(m + 1)
        pmf[m] = 1.0
        return pmf
    return betabinomial_pmf(m, n + 1 - rank, rank)


@dataclass(frozen=True)
class CoverageTest:
    """One audited figure: m instances of which ``covered`` fell in their sets, against what a
    valid calibration of n scores at rank l predicts."""

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
    def band_coverage(self) -> tuple[float, float] | None:
        return None if self.m == 0 else (self.band[0] / self.m, self.band[1] / self.m)

    @property
    def in_band(self) -> bool:
        return self.band[0] <= self.covered <= self.band[1]


def coverage_test(covered: int, m: int, n: int, epsilon: float, level: float = BAND_LEVEL) -> CoverageTest:
    """The band and the one-sided p-value of ``covered`` out of ``m`` (Theorem 1, eq. 5)."""
    if not 0 <= covered <= m:
        raise ValueError(f"covered must be in [0, m], got {covered} of {m}")
    pmf = covered_count_pmf(m, n, epsilon)
    p_value = float(min(1.0, pmf[: covered + 1].sum()))
    band = central_interval(pmf, level)
    return CoverageTest(m, covered, n, conformal_rank(n, epsilon), epsilon, band, p_value)


def pooled_band(tests: Sequence[CoverageTest], level: float = BAND_LEVEL) -> tuple[int, int]:
    """A band for the covered count pooled over several units (keypoints, objects) whatever their
    dependence: each unit's count lies in its band at level 1 - (1-level)/U with that
    probability, so by the union bound all do, and their sum lies in the sum of the bands,
    with probability at least ``level``. Conservative (the units share calibration images)."""
    if not tests:
        return 0, 0
    unit_level = 1.0 - (1.0 - level) / len(tests)
    bands = [central_interval(covered_count_pmf(t.m, t.n, t.epsilon), unit_level) for t in tests]
    return sum(low for low, _ in bands), sum(high for _, high in bands)


def bonferroni_p_value(tests: Sequence[CoverageTest]) -> float:
    """The global test of "no unit's coverage is low": min(1, U * min p), valid under any dependence."""
    return 1.0 if not tests else min(1.0, len(tests) * min(t.p_value for t in tests))


def recalibration_size(
    epsilon: float, tolerance: float = RECALIBRATION_TOLERANCE, level: float = BAND_LEVEL
) -> int:
    """The smallest n with bounded sets (l >= 1, i.e. 1/(n+1) <= eps) whose conditional coverage
    stays above 1 - eps - tolerance with probability ``level``:
    P(Beta(n+1-l, l) < 1 - eps - tolerance) <= 1 - level (eq. 5). Found by bisection (the
    probability shrinks as n grows, up to the floor in l)."""
    target = 1.0 - epsilon - tolerance
    floor = conformal_floor(epsilon)
    if target <= 0 or floor >= _MAX_RECALIBRATION_N:
        return floor

    def enough(n: int) -> bool:
        rank = conformal_rank(n, epsilon)
        return rank >= 1 and beta_cdf(target, n + 1 - rank, rank) <= 1.0 - level

    low = high = floor
    while not enough(high):
        low, high = high, high * 2
        if high > _MAX_RECALIBRATION_N:
            return _MAX_RECALIBRATION_N
    while low < high:
        middle = (low + high) // 2
        if enough(middle):
            high = middle
        else:
            low = middle + 1
    return high


def conformal_floor(epsilon: float) -> int:
    """The smallest n with bounded sets at ``epsilon``: floor((n+1) eps) >= 1."""
    exact = Fraction(repr(float(epsilon)))  # the decimal the caller wrote, as conformal_rank reads it
    return max(0, math.ceil(1 / exact) - 1)
