"""Coverage guarantees of Theorem 1 and the calibration-conditional (PAC) rank.

Marginally 1 - eps <= 1 - t/(n+1) <= 1 - eps + 1/(n+1) (eq. 4); conditionally, coverage ~
Beta(n+1-t, t) (eq. 5), whose CDF is a binomial tail summed exactly in log space (no scipy). PAC:
the largest t with P(Binomial(n, eps) <= t-1) <= delta, never above floor((n+1) eps); every eps and
delta in (0, 1) has an answer (1 - p is never formed where it would round).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from .threshold import _check_epsilon, column_thresholds, conformal_rank, labeled_counts, threshold_for_rank

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
        return 0.0 if self.t == 0 else binomial_cdf(self.t - 1, self.n, self.epsilon)

    @property
    def pac_level(self) -> float | None:
        """1 - delta when a PAC guarantee was requested."""
        return None if self.delta is None else 1.0 - self.delta

    def as_dict(self) -> dict[str, object]:
        names = ("unbounded", "marginal_lower", "marginal_coverage", "marginal_upper", "beta_a", "beta_b")
        return asdict(self) | {
            name: getattr(self, name) for name in (*names, "pac_failure_probability", "pac_level")
        }


@dataclass(frozen=True)
class Calibration:
    """A threshold and the guarantee that comes with it."""

    threshold: float
    guarantee: CoverageGuarantee


def coverage_guarantee(n: int, epsilon: float, delta: float | None = None) -> CoverageGuarantee:
    """The rank t (marginal, or PAC when delta is given) and its guarantee for n scores; the PAC rank
    is capped at the marginal one (above it for delta > ~0.37), which 1 - eps must keep bounding."""
    t = conformal_rank(n, epsilon)
    if delta is not None:
        t = min(t, pac_rank(n, epsilon, delta))
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
        if _pac_failure_at_most(n, middle, epsilon, delta):
            low = middle
        else:
            high = middle - 1
    return low


def beta_cdf(x: float, a: int, b: int) -> float:
    """P(Beta(a, b) <= x) for integers a, b >= 1, via P(Binomial(a+b-1, 1-x) <= b-1)."""
    if a < 1 or b < 1:
        raise ValueError(f"Beta parameters must be integers >= 1, got ({a}, {b})")
    return math.exp(_log_binomial_tails(b - 1, a + b - 1, 1.0 - x, x)[0])


def binomial_cdf(m: int, n: int, p: float) -> float:
    """P(Binomial(n, p) <= m), summing whichever tail is smaller in log space."""
    return math.exp(_log_binomial_tails(m, n, p, 1.0 - p)[0])


def _pac_failure_at_most(n: int, t: int, epsilon: float, delta: float) -> bool:
    """Whether P(Binomial(n, eps) <= t-1) <= delta, decided where it is exact: in log space near 0
    (exp would lose a subnormal delta's digits), by its complement near 1; the reported value must
    not exceed delta either, so a tie within rounding refuses t."""
    log_failure, log_success = _log_binomial_tails(t - 1, n, epsilon, 1.0 - epsilon)
    precise = log_failure <= math.log(delta) if delta <= 0.5 else log_success >= math.log1p(-delta)
    return precise and math.exp(log_failure) <= delta


def _log_binomial_tails(m: int, n: int, p: float, q: float) -> tuple[float, float]:
    """(log P(Binomial(n, p) <= m), log P(Binomial(n, p) > m)); log 0 is -inf. q = 1 - p is given
    apart because 1 - p rounds away a tiny p (the smaller of p and q must be exact); the smaller
    tail is summed, the other is its complement."""
    if m < 0:
        return -math.inf, 0.0
    if m >= n or p <= 0.0:
        return 0.0, -math.inf
    if q <= 0.0:
        return -math.inf, 0.0
    if m < n * p:
        lower = _log_lower_tail(m, n, p, q)
        return lower, _log_one_minus_exp(lower)
    upper = _log_lower_tail(n - m - 1, n, q, p)  # P(X > m) = P(n - X <= n - m - 1), n - X ~ Bin(n, q)
    return _log_one_minus_exp(upper), upper


def _log_one_minus_exp(x: float) -> float:
    """log(1 - e^x) for x <= 0, accurate at both ends."""
    if x >= 0.0:
        return -math.inf
    return math.log(-math.expm1(x)) if x > -math.log(2.0) else math.log1p(-math.exp(x))


def _log_lower_tail(m: int, n: int, p: float, q: float) -> float:
    """log P(Binomial(n, p) <= m) for 0 <= m < n, 0 < p, q < 1, p + q = 1; both logs come from the
    smaller of p and q, the exact one."""
    small = min(p, q)
    log_small, log_large = math.log(small), math.log1p(-small)
    log_p, log_q = (log_small, log_large) if p <= q else (log_large, log_small)
    width = int(_TAIL_WIDTH_SD * math.sqrt(n * small * (1.0 - small))) + 50
    j = np.arange(max(0, m - width), m + 1, dtype=np.float64)
    log_terms = (
        math.lgamma(n + 1)
        - _log_gamma(j + 1).astype(np.float64)
        - _log_gamma(n - j + 1).astype(np.float64)
        + j * log_p
        + (n - j) * log_q
    )
    largest = log_terms.max()
    return float(largest + math.log(np.exp(log_terms - largest).sum()))
