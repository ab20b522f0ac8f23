"""The evaluation's exact coverage laws and rank correlation, against scipy."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from service.conformal.laws import beta_interval, beta_quantile, betabinomial_pmf, central_interval
from service.evaluation.adaptiveness import average_ranks, spearman
from service.evaluation.coverage import GroupCoverage


@pytest.mark.parametrize(("m", "a", "b"), [(1, 1, 1), (50, 30, 4), (400, 451, 50), (1000, 900, 100)])
def test_betabinomial_pmf_and_interval_match_scipy(m: int, a: int, b: int) -> None:
    pmf = betabinomial_pmf(m, a, b)
    np.testing.assert_allclose(pmf, stats.betabinom.pmf(np.arange(m + 1), m, a, b), atol=1e-12)
    low, high = central_interval(pmf)
    assert (low, high) == tuple(int(v) for v in stats.betabinom.ppf([0.025, 0.975], m, a, b))


@pytest.mark.parametrize(("q", "a", "b"), [(0.025, 451, 50), (0.5, 26, 2), (0.975, 3, 1)])
def test_beta_quantile_matches_scipy(q: float, a: int, b: int) -> None:
    assert beta_quantile(q, a, b) == pytest.approx(stats.beta.ppf(q, a, b), abs=1e-8)
    low, high = beta_interval(a, b)
    assert low < beta_quantile(0.5, a, b) < high


def test_spearman_with_ties_matches_scipy() -> None:
    rng = np.random.default_rng(0)
    x = rng.integers(0, 5, 200).astype(float)
    y = x + rng.integers(0, 3, 200)
    y[:10] = np.inf  # unbounded sets rank last
    np.testing.assert_allclose(average_ranks(x), stats.rankdata(x))
    assert spearman(x, y) == pytest.approx(stats.spearmanr(x, y).statistic, abs=1e-12)
    assert math.isnan(spearman(np.ones(10), np.arange(10.0)))


def test_group_coverage_predictive_interval() -> None:
    inside = GroupCoverage("k", n=500, t=50, m=400, covered=360)
    outside = GroupCoverage("k", n=500, t=50, m=400, covered=330)
    assert inside.inside_predictive() and not outside.inside_predictive()
    assert 0.4 < inside.chance_at_least(0.9) < 0.8
    low, high = inside.band()
    assert (round(low * 400), round(high * 400)) == tuple(
        int(v) for v in stats.betabinom.ppf([0.025, 0.975], 400, 451, 50)
    )
    assert GroupCoverage("k", n=5, t=0, m=9, covered=9).band() == (1.0, 1.0)  # unbounded sets
