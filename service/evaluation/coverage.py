"""Validity: per-keypoint (and per-object) empirical coverage of a labeled batch against the exact law
of Theorem 1 (Yang & Pavone): given the calibration set the coverage is Beta(n+1-t, t), so the covered
count of m test points is BetaBinomial(m, n+1-t, t). A group is *inside* when its count lies in the
central 95% interval of that law; the plain Beta interval ignores the test noise (stricter)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.conformal import CoverageGuarantee, binomial_cdf
from service.conformal.laws import beta_interval, betabinomial_pmf, central_interval
from service.evaluation.rows import Rows

LEVEL = 0.95


@dataclass(frozen=True)
class GroupCoverage:
    """Coverage of one keypoint (or one object, simultaneously) on the test split."""

    name: str
    n: int  # calibration size
    t: int  # rank
    m: int  # test size
    covered: int

    @property
    def coverage(self) -> float:
        return self.covered / self.m if self.m else float("nan")

    @property
    def unbounded(self) -> bool:
        return self.t == 0

    def law(self) -> np.ndarray:
        """pmf of the covered count: BetaBinomial(m, n+1-t, t)."""
        return betabinomial_pmf(self.m, self.n + 1 - self.t, self.t)

    def band(self) -> tuple[float, float]:
        """Central 95% interval of the empirical coverage of m test points under the law: where
        the coverage falls when the calibration is valid (unbounded sets: always 1)."""
        if self.unbounded or not self.m:
            return 1.0, 1.0
        low, high = central_interval(self.law(), LEVEL)
        return low / self.m, high / self.m

    def inside_predictive(self) -> bool:
        low, high = self.band()
        return low - 1e-12 <= self.coverage <= high + 1e-12

    def inside_beta(self) -> bool:
        if self.unbounded:
            return self.covered == self.m
        low, high = beta_interval(self.n + 1 - self.t, self.t, LEVEL)
        return low <= self.coverage <= high

    def chance_at_least(self, target: float) -> float:
        """P(empirical coverage >= target) under the law (what PAC predicts we observe)."""
        if self.unbounded:
            return 1.0
        need = int(np.ceil(target * self.m - 1e-9))
        return float(self.law()[need:].sum())

    def not_significantly_below(self, target: float, alpha: float = 0.05) -> bool:
        """One-sided binomial test: is covered count consistent with true coverage >= target?"""
        return binomial_cdf(self.covered, self.m, target) > alpha


@dataclass(frozen=True)
class ValiditySummary:
    kind: str
    epsilon: float
    scope: str
    delta: float | None
    groups: tuple[GroupCoverage, ...]

    @property
    def label(self) -> str:
        """The scope as a reader names it: keypoint, object, or keypoint with the PAC rank."""
        return f"keypoint, PAC delta={self.delta}" if self.scope == "pac" else self.scope

    @property
    def target(self) -> float:
        return 1 - self.epsilon

    def coverages(self) -> np.ndarray:
        return np.array([g.coverage for g in self.groups if g.m])

    def average(self, of) -> float:
        """The mean of ``of`` (a share when it says yes or no) over the groups with test points."""
        values = [of(g) for g in self.groups if g.m]
        return float(np.mean(values)) if values else float("nan")

    def one_calibration(self) -> tuple[float, float]:
        """Where one calibration puts a keypoint's (object's) coverage, 95% central: the Beta law
        of the group with the median n (lower median), whatever the test batch."""
        tested = sorted((g for g in self.groups if g.m), key=lambda g: g.n)
        if not tested:
            return float("nan"), float("nan")
        median = tested[(len(tested) - 1) // 2]
        if median.unbounded:
            return 1.0, 1.0
        return beta_interval(median.n + 1 - median.t, median.t, LEVEL)


def unit_groups(
    rows: Rows,
    covered: np.ndarray,
    guarantees: tuple[CoverageGuarantee, ...],
    units: list[tuple[str, tuple[int, ...]]],
) -> tuple[GroupCoverage, ...]:
    """Per unit (a keypoint, or an object: its name and keypoint channels): the instances with all its
    keypoints labeled, and of them those with all covered at once."""
    groups = []
    for name, keypoints in units:
        unit = np.isin(rows.channel, keypoints)
        ids, index = np.unique(rows.instance[unit], return_inverse=True)
        complete = np.bincount(index, weights=rows.labeled[unit], minlength=len(ids)) == len(keypoints)
        all_covered = np.bincount(index, weights=covered[unit], minlength=len(ids)) == len(keypoints)
        n, t = guarantees[keypoints[0]].n, guarantees[keypoints[0]].t
        groups.append(GroupCoverage(name, n, t, int(complete.sum()), int((all_covered & complete).sum())))
    return tuple(groups)
