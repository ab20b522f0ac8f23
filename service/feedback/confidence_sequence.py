"""An anytime-valid confidence sequence for a mean coverage, and the alarm it proves.

Votes x_i in [0, 1]. Against "each vote's mean is at least p" the mixture M_n(p) = (1/J) sum_j
prod_i (q_j / p)^x_i ((1 - q_j) / (1 - p))^(1 - x_i), q_j < p, is a nonnegative supermartingale, so
by Ville P(sup_n M_n(p) >= 1/a) <= a; the bounds are the extreme p not rejected at level a.
``CoverageAlarm``: rung i tests "mean >= the u_i quantile of the coverage law Beta(n + 1 - t, t)" with
an e-process alarming at 1 / a_i, raised once every rung has: P(alarm) <= u_0 + sum_i (u_(i+1) - u_i) a_i.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from service.conformal import beta_cdf

#: alternatives of the mixture: relative gaps to the candidate mean
_GAPS = np.geomspace(1e-3, 0.999, 48)
#: candidate means scanned for the bounds
_CANDIDATES = np.linspace(0.0, 1.0, 2001)[1:-1]
#: the alarm's bets forget the votes they are sized from: half their weight is on the last 69
_BET_MEMORY = 0.99
#: the alarm's rungs: quantile levels of a threshold's coverage law, as multiples of the alarm level
RUNGS = (0.2, 1.0, 5.0)


@dataclass(frozen=True)
class CoverageBounds:
    votes: int
    mean: float | None
    lower: float
    upper: float


def _log_mixture(total: np.ndarray, count: np.ndarray | int, p: np.ndarray) -> np.ndarray:
    q = p * (1.0 - _GAPS)
    terms = total * np.log(q / p) + (count - total) * np.log((1.0 - q) / (1.0 - p))
    top = terms.max(axis=-1)
    return top + np.log(np.exp(terms - top[..., None]).mean(axis=-1))


def coverage_bounds(total: float, count: int, level: float) -> CoverageBounds:
    """Two-sided confidence sequence at ``level`` (each side level / 2) for the votes' mean."""
    if count == 0:
        return CoverageBounds(0, None, 0.0, 1.0)
    limit = math.log(2.0 / level)
    above = _log_mixture(np.array([total], dtype=np.float64), count, _CANDIDATES[:, None]) < limit
    mirror = np.array([count - total], dtype=np.float64)
    below = _log_mixture(mirror, count, 1.0 - _CANDIDATES[:, None]) < limit
    upper = float(_CANDIDATES[above].max()) if above.any() else 0.0
    lower = float(_CANDIDATES[below].min()) if below.any() else 1.0
    # an end of the scan not rejected: the bound is the end of [0, 1] (all covered: upper 1, not 0.9995)
    lower = 0.0 if lower == _CANDIDATES[0] else lower
    upper = 1.0 if upper == _CANDIDATES[-1] else upper
    return CoverageBounds(count, total / count, lower, upper)


@lru_cache(maxsize=4096)  # a few (n, t) per version, and 60 Beta cdfs each: read per labelled unit
def promised_floor(n: int, t: int, epsilon: float, delta: float | None, band_level: float) -> float:
    """1 - epsilon with a PAC delta, else the ``band_level`` quantile of Beta(n + 1 - t, t)."""
    if delta is not None:
        return 1.0 - epsilon
    if t == 0:
        return 1.0
    low, high = 0.0, 1.0
    for _ in range(60):
        middle = (low + high) / 2
        if beta_cdf(middle, n + 1 - t, t) < band_level:
            low = middle
        else:
            high = middle
    return low


def alarm_rungs(level: float) -> tuple[tuple[float, float], ...]:
    """Per rung (u_i, a_i): floor at the u_i quantile of the coverage law, alarm at 1 / a_i; the rungs
    of ``RUNGS`` below 0.5 share what u_0 leaves: u_0 + sum_i (u_(i+1) - u_i) a_i <= level, u_m = 1."""
    # level < 0.5: one rung at least
    quantiles = [level * multiple for multiple in RUNGS if level * multiple < 0.5]
    share = (level - quantiles[0]) / len(quantiles)
    uppers = [*quantiles[1:], 1.0]
    return tuple((u, min(1.0, share / (upper - u))) for u, upper in zip(quantiles, uppers, strict=True))


def rung_floors(n: int, t: int, epsilon: float, delta: float | None, level: float) -> tuple[float, ...]:
    """A threshold's floor on each rung of the alarm at ``level`` (with a PAC delta: 1 - epsilon on each)."""
    return tuple(promised_floor(n, t, epsilon, delta, u) for u, _ in alarm_rungs(level))


class CoverageAlarm:
    """Raised once every rung's e-process has been, then for good (module doc)."""

    def __init__(self, level: float) -> None:
        self._rungs = [BettingEProcess(a) for _, a in alarm_rungs(level)]
        self.raised = False

    def observe(self, vote: float, floors: Sequence[float]) -> bool:
        """Add one vote in [0, 1] and its floor on each rung; whether the alarm is raised."""
        for rung, floor in zip(self._rungs, floors, strict=True):
            rung.observe(vote, floor)
        self.raised = self.raised or all(rung.raised for rung in self._rungs)
        return self.raised


class BettingEProcess:
    """One rung: K_t = prod (1 + lambda_t (f_t - x_t)) (Waudby-Smith & Ramdas 2023), the bet from the
    discounted mean and variance of earlier votes; by Ville P(ever K_t >= 1 / alpha) <= alpha."""

    def __init__(self, alpha: float) -> None:
        self._limit = math.log(1.0 / alpha)
        self.log_wealth, self.count, self.raised = 0.0, 0, False
        self._sum, self._squares, self._weight = 0.0, 0.25, 0.0  # discounted sums; a prior variance 1/4

    def observe(self, vote: float, floor: float) -> bool:
        """Add one vote in [0, 1] and the coverage it promised; whether the e-process has crossed."""
        if floor <= 0.0 or floor >= 1.0:  # nothing promised, or nothing below 1 to prove
            return self.raised
        prior = _BET_MEMORY**self.count  # a prior vote at the floor, forgotten as the others
        mean = (self._sum + prior * floor) / (self._weight + prior)
        variance = self._squares / (self._weight + prior)
        gap = floor - mean
        bet = min(max(gap / (variance + gap * gap), 0.0), 0.5 / (1.0 - floor))
        self.log_wealth += math.log1p(bet * (floor - vote))
        self.count += 1
        self._sum = _BET_MEMORY * self._sum + vote
        self._squares = _BET_MEMORY * self._squares + (vote - mean) ** 2
        self._weight = _BET_MEMORY * self._weight + 1
        self.raised = self.raised or self.log_wealth >= self._limit
        return self.raised
