"""Coverage guarantees of Theorem 1 and the calibration-conditional (PAC) rank.

Marginally 1 - eps <= 1 - t/(n+1) = P(cover) <= 1 - eps + 1/(n+1)  (eq. 4);
conditionally on the calibration set, coverage ~ Beta(n+1-t, t)  (eq. 5).
For integer parameters the Beta CDF is a binomial tail,
P(Beta(a, b) <= x) = P(Binomial(a+b-1, x) >= a), summed here exactly in log
space (no scipy at run time, stable for n up to 10^6 and beyond).

PAC: given delta, use the largest t with P(Beta(n+1-t, t) < 1-eps) <= delta,
i.e. P(Binomial(n, eps) <= t-1) <= delta; t = 0 (unbounded set) always qualifies.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from .threshold import (
    _check_epsilon,
    column_thresholds,
    conformal_rank,
    labeled_counts,
    threshold_for_rank,
)

_log_gamma = np.frompyfunc(math.lgamma, 1, 1)
_TAIL_WIDTH_SD = 40  # terms further than this from the tail's largest term are < e^-800 of it


@dataclass(frozen=True)
class CoverageGuarantee:
    """What a threshold from n calibration scores at rank t guarantees (Theorem 1)."""

    n: int
    t: int
    epsilon: float
    delta: float | None = None

    @property
    def unbounded(self) -> bool:
        return self.t == 0

    @property
    def marginal_lower(self) -> float:
        return 1.0 - self.epsilon

    @property
    def marginal_coverage(self) -> float:
        """The exact marginal coverage 1 - t/(n+1) (>= marginal_lower)."""
        return 1.0 - self.t / (self.n + 1)

    @property
    def marginal_upper(self) -> float:
        """1 - eps + 1/(n+1) (eq. 4, scores without ties); 1 - t/(n+1) for a smaller PAC t."""
        theorem_bound = 1.0 - self.epsilon + 1.0 / (self.n + 1)
        return min(1.0, max(theorem_bound, self.marginal_coverage))

    @property
    def beta_a(self) -> int:
        return self.n + 1 - self.t

    @property
    def beta_b(self) -> int:
        return self.t

    @property
    def pac_failure_probability(self) -> float:
        """P(conditional coverage < 1 - eps) = P(Beta(n+1-t, t) < 1 - eps); 0 when t = 0."""
        return _pac_failure(self.n, self.t, self.epsilon)

    @property
    def pac_level(self) -> float | None:
        """1 - delta when a PAC guarantee was requested."""
        return None if self.delta is None else 1.0 - self.delta

    def as_dict(self) -> dict[str, object]:
        names = ("unbounded", "marginal_lower", "marginal_coverage", "marginal_upper")
        extra = {name: getattr(self, name) for name in names}
        extra |= {"beta_a": self.beta_a, "beta_b": self.beta_b}
        extra |= {"pac_failure_probability": self.pac_failure_probability}
        extra |= {"pac_level": self.pac_level}
        return asdict(self) | extra


@dataclass(frozen=True)
class Calibration:
    """A threshold and the guarantee that comes with it."""

    threshold: float
    guarantee: CoverageGuarantee


def coverage_guarantee(n: int, epsilon: float, delta: float | None = None) -> CoverageGuarantee:
    """The rank t (marginal, or PAC when delta is given) and its guarantee for n scores."""
    t = conformal_rank(n, epsilon) if delta is None else pac_rank(n, epsilon, delta)
    return CoverageGuarantee(n=n, t=t, epsilon=float(epsilon), delta=delta)


def calibrate(scores: np.ndarray, epsilon: float, delta: float | None = None) -> Calibration:
    """Threshold and guarantee for 1-D calibration scores (NaN = unlabeled, ignored)."""
    scores = np.asarray(scores, dtype=np.float64).ravel()
    n = int(np.count_nonzero(~np.isnan(scores)))
    guarantee = coverage_guarantee(n, epsilon, delta)
    return Calibration(threshold_for_rank(scores, guarantee.t), guarantee)


def calibrate_columns(
    score_matrix: np.ndarray, epsilon: float, delta: float | None = None
) -> tuple[np.ndarray, list[CoverageGuarantee]]:
    """Per-column thresholds (G,) and guarantees for (n_instances, G) scores with NaNs."""
    counts = labeled_counts(score_matrix)
    guarantees = [coverage_guarantee(int(n), epsilon, delta) for n in counts]
    ranks = np.array([g.t for g in guarantees], dtype=np.intp)
    return column_thresholds(score_matrix, ranks), guarantees


def pac_rank(n: int, epsilon: float, delta: float) -> int:
    """Largest t in [0, n] with P(Beta(n+1-t, t) < 1 - eps) <= delta (binary search)."""
    _check_epsilon(epsilon)
    if not 0 < delta < 1:
        raise ValueError(f"delta must be in (0, 1), got {delta}")
    low, high = 0, n  # invariant: failure(low) <= delta
    while low < high:
        middle = (low + high + 1) // 2
        if _pac_failure(n, middle, epsilon) <= delta:
            low = middle
        else:
            high = middle - 1
    return low


def beta_cdf(x: float, a: int, b: int) -> float:
    """P(Beta(a, b) <= x) for integers a, b >= 1, via P(Binomial(a+b-1, x) >= a)."""
    if a < 1 or b < 1:
        raise ValueError(f"Beta parameters must be integers >= 1, got ({a}, {b})")
    return binomial_cdf(b - 1, a + b - 1, 1.0 - x)


def binomial_cdf(m: int, n: int, p: float) -> float:
    """P(Binomial(n, p) <= m), summing whichever tail is smaller in log space."""
    if m < 0:
        return 0.0
    if m >= n or p <= 0.0:
        return 1.0
    if p >= 1.0:
        return 0.0
    if m < n * p:
        return math.exp(_log_lower_tail(m, n, p))
    return -math.expm1(_log_lower_tail(n - m - 1, n, 1.0 - p))


def _pac_failure(n: int, t: int, epsilon: float) -> float:
    return 0.0 if t == 0 else binomial_cdf(t - 1, n, epsilon)


def _log_lower_tail(m: int, n: int, p: float) -> float:
    """log P(Binomial(n, p) <= m) for 0 <= m < n, 0 < p < 1."""
    width = int(_TAIL_WIDTH_SD * math.sqrt(n * p * (1 - p))) + 50
    j = np.arange(max(0, m - width), m + 1, dtype=np.float64)
    log_terms = (
        math.lgamma(n + 1)
        - _log_gamma(j + 1).astype(np.float64)
        - _log_gamma(n - j + 1).astype(np.float64)
        + j * math.log(p)
        + (n - j) * math.log1p(-p)
    )
    largest = log_terms.max()
    return float(largest + math.log(np.exp(log_terms - largest).sum()))
