"""The audit's statistics against scipy and against simulation of the conformal procedure."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from service.conformal import beta_cdf, conformal_rank, conformal_threshold
from service.conformal.laws import betabinomial_pmf, central_interval
from service.monitoring.coverage_law import (
    conformal_floor,
    coverage_test,
    covered_count_pmf,
    pooled_test,
    recalibration_size,
)
from service.monitoring.multiple_testing import holm_adjusted


@pytest.mark.parametrize("m, a, b", [(0, 1, 1), (1, 2.5, 0.5), (10, 541, 60), (52, 9001, 1000), (500, 3, 7)])
def test_betabinom_pmf_matches_scipy(m: int, a: float, b: float) -> None:
    k = np.arange(m + 1)
    expected = stats.betabinom(m, a, b).pmf(k)
    assert np.allclose(betabinomial_pmf(m, a, b), expected, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("m, n, epsilon", [(6, 600, 0.1), (52, 600, 0.05), (200, 99, 0.2), (30, 9, 0.05)])
def test_band_and_p_value_are_the_beta_binomial_of_theorem_1(m: int, n: int, epsilon: float) -> None:
    rank = conformal_rank(n, epsilon)
    law = stats.betabinom(m, n + 1 - rank, rank) if rank else None
    for covered in range(0, m + 1, max(1, m // 7)):
        test = coverage_test(covered, m, n, epsilon)
        if law is None:  # unbounded sets: all is covered, nothing is low
            assert test.band == (m, m) and test.p_value == (1.0 if covered == m else 0.0)
            continue
        assert test.p_value == pytest.approx(law.cdf(covered), rel=1e-8, abs=1e-14)
        low, high = test.band
        assert law.cdf(low - 1) <= 0.025 + 1e-12 and law.sf(high) <= 0.025 + 1e-12
        assert law.cdf(low) > 0.025 or low == m  # no narrower band: the bounds are the tightest
        assert law.sf(high - 1) > 0.025 or high == 0


def test_the_band_holds_when_the_calibration_is_valid() -> None:
    """Simulate the procedure: exchangeable calibration and test scores; the test batch's
    coverage falls in its band at least 95% of the time, and p < 0.05 at most 5%."""
    rng = np.random.default_rng(3)
    n, m, epsilon, runs = 200, 40, 0.1, 3000
    inside = low_p = 0
    for _ in range(runs):
        scores = rng.exponential(size=n + m)
        threshold = conformal_threshold(scores[:n], epsilon)
        covered = int(np.count_nonzero(scores[n:] <= threshold))
        test = coverage_test(covered, m, n, epsilon)
        inside += test.in_band
        low_p += test.p_value <= 0.05
    assert inside / runs >= 0.95 - 3 * np.sqrt(0.05 * 0.95 / runs)
    assert low_p / runs <= 0.05 + 3 * np.sqrt(0.05 * 0.95 / runs)


def test_shifted_test_scores_give_small_p_values() -> None:
    rng = np.random.default_rng(4)
    n, m, epsilon = 600, 30, 0.1
    threshold = conformal_threshold(rng.exponential(size=n), epsilon)
    covered = int(np.count_nonzero(rng.exponential(size=m) * 3 <= threshold))  # scores 3x larger
    test = coverage_test(covered, m, n, epsilon)
    assert not test.in_band and test.p_value < 1e-4


def test_central_band_of_a_point_mass() -> None:
    pmf = np.zeros(5)
    pmf[3] = 1
    assert central_interval(pmf) == (3, 3)
    assert covered_count_pmf(4, 5, 0.1).tolist() == [0, 0, 0, 0, 1]  # n + 1 < 1/eps: unbounded


def _pooled_runs(runs: int, shift: float, seed: int) -> list:
    """Pooled tests of 6 keypoints calibrated on 300 shared images and audited on 150 others;
    an image's keypoints share its difficulty (scores correlated within an image), and
    ``shift`` makes the audited images that much harder."""
    rng = np.random.default_rng(seed)
    n, m, units, epsilon = 300, 150, 6, 0.1
    found = []
    for _ in range(runs):
        difficulty = rng.exponential(size=(n + m, 1))
        scores = difficulty + 0.5 * rng.exponential(size=(n + m, units))
        scores[n:] *= 1 + shift
        tests, covered = [], []
        for u in range(units):
            threshold = conformal_threshold(scores[:n, u], epsilon)
            inside = scores[n:, u] <= threshold
            covered.append(inside.astype(int))
            tests.append(coverage_test(int(inside.sum()), m, n, epsilon))
        found.append(pooled_test(tests, np.ones((m, units), dtype=int), np.stack(covered, axis=1)))
    return found


def test_pooled_band_holds_under_dependence() -> None:
    """Keypoints share calibration images and an audited image's keypoints its difficulty: the
    pooled band still holds about 95% of the time; the union-bound band it replaced was twice
    as wide, too wide to flag what the next test flags."""
    pooled = _pooled_runs(800, 0.0, 5)
    assert np.mean([p.in_band for p in pooled]) >= 0.94
    assert np.mean([p.p_value <= 0.05 for p in pooled]) <= 0.06
    widths = [p.band[1] - p.band[0] for p in pooled]
    assert np.median(widths) < 0.12


def test_pooled_band_flags_a_harder_batch() -> None:
    flagged = [p.p_value <= 0.05 and not p.in_band for p in _pooled_runs(200, 0.3, 6)]
    assert np.mean(flagged) >= 0.7


def test_holm_matches_the_step_down_by_hand() -> None:
    p = [0.01, 0.04, 0.03, 0.005]
    # sorted 0.005, 0.01, 0.03, 0.04 -> x4, x3, x2, x1 -> 0.02, 0.03, 0.06, 0.06 (monotone)
    assert holm_adjusted(p).tolist() == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm_adjusted([]).size == 0
    assert np.isnan(holm_adjusted([np.nan, 0.01])[0]) and holm_adjusted([np.nan, 0.01])[1] == 0.01


@pytest.mark.parametrize("epsilon", [0.05, 0.1, 0.2])
def test_recalibration_size_is_the_smallest_n_that_keeps_coverage(epsilon: float) -> None:
    n = recalibration_size(epsilon)
    target = 1 - epsilon - 0.02

    def failure(size: int) -> float:
        rank = conformal_rank(size, epsilon)
        return stats.beta(size + 1 - rank, rank).cdf(target)

    assert 1 / (n + 1) <= epsilon and failure(n) <= 0.05
    assert failure(n - 1) > 0.05
    assert conformal_rank(conformal_floor(epsilon), epsilon) == 1
    assert conformal_rank(conformal_floor(epsilon) - 1, epsilon) == 0
    assert beta_cdf(target, n + 1 - conformal_rank(n, epsilon), conformal_rank(n, epsilon)) <= 0.05


def test_extreme_epsilons_have_answers() -> None:
    assert recalibration_size(1e-300) == conformal_floor(1e-300) >= 10**299
    assert recalibration_size(0.99) == conformal_floor(0.99) == 1
    test = coverage_test(3, 3, 10**6, 1e-9)  # l = 0: unbounded sets cover everything
    assert test.band == (3, 3) and test.p_value == 1.0
