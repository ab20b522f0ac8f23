"""The two-sample tests of service/monitoring/two_sample.py against scipy (a test dependency only)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from service.monitoring.multiple_testing import holm_rejections
from service.monitoring.two_sample import (
    EXACT_LIMIT,
    kolmogorov_sf,
    ks_asymptotic_p_value,
    ks_p_value,
    ks_statistic,
    population_stability_index,
    quantile_bin_edges,
)

SIZES = [
    (1, 1),
    (3, 8),
    (5, 7),
    (9, 500),
    (20, 500),
    (40, 200),
    (100, 100),
    (60, 600),
    (300, 500),
    (2000, 600),
]


@pytest.mark.parametrize(("n", "m"), SIZES)
@pytest.mark.parametrize("shift", [0.0, 0.4, 1.5])
def test_ks_matches_scipy(n: int, m: int, shift: float):
    rng = np.random.default_rng(n * 1000 + m)
    reference = np.sort(rng.normal(size=m))
    live = rng.normal(shift, 1.3, size=n)
    method = "exact" if n * m <= EXACT_LIMIT else "asymp"
    expected = stats.ks_2samp(live, reference, method=method)
    statistic = ks_statistic(reference, live)
    assert statistic == pytest.approx(expected.statistic, abs=1e-12)
    p_value = ks_p_value(statistic, n, m)
    if method == "exact":
        # computed as 1 - P(inside): about 1e-14 of cancellation
        assert p_value == pytest.approx(expected.pvalue, rel=1e-8, abs=1e-12)
    else:
        # scipy's asymptotic form is kstwo(round(e)); ours Kolmogorov's law with Stephens' correction
        assert p_value == pytest.approx(expected.pvalue, rel=0.05, abs=1e-6)


@pytest.mark.parametrize("x", [0.05, 0.3, 0.5, 0.8, 0.99, 1.0, 1.2, 2.0, 3.5, 6.0])
def test_kolmogorov_law_matches_scipy(x: float):
    assert kolmogorov_sf(x) == pytest.approx(stats.kstwobign.sf(x), rel=1e-10, abs=1e-300)


def test_asymptotic_p_value_is_close_to_exact_where_both_apply():
    rng = np.random.default_rng(7)
    reference, live = np.sort(rng.normal(size=400)), rng.normal(0.2, 1.0, size=200)
    statistic = ks_statistic(reference, live)
    exact = stats.ks_2samp(live, reference, method="exact").pvalue
    assert ks_asymptotic_p_value(statistic, 200, 400) == pytest.approx(exact, rel=0.05)


def test_identical_samples_have_p_value_one():
    values = np.linspace(0, 1, 50)
    assert ks_statistic(values, values) == 0.0
    assert ks_p_value(0.0, 50, 50) == 1.0


def test_empty_sample_is_refused():
    with pytest.raises(ValueError, match="at least one value"):
        ks_p_value(0.5, 0, 10)


def test_psi_is_zero_for_the_reference_itself_and_grows_with_a_shift():
    rng = np.random.default_rng(3)
    reference = rng.normal(size=2000)
    edges = quantile_bin_edges(reference)
    assert population_stability_index(reference, reference, edges) == pytest.approx(0.0, abs=1e-12)
    small = population_stability_index(reference, rng.normal(0.1, 1, size=2000), edges)
    large = population_stability_index(reference, rng.normal(1.0, 1, size=2000), edges)
    assert small < 0.1 < 0.25 < large


def test_psi_matches_its_definition_on_hand_counted_bins():
    reference = np.arange(10.0)  # edges at 0.9, 1.8, ...: one reference value per bin
    live = np.array([0.0, 0.0, 0.0, 0.0, 9.0])  # 4/5 in the first bin, 1/5 in the last
    shares = np.full(10, 1e-4)
    shares[0], shares[-1] = 0.8, 0.2
    expected = float(np.sum((shares - 0.1) * np.log(shares / 0.1)))
    assert population_stability_index(reference, live, quantile_bin_edges(reference)) == pytest.approx(
        expected
    )


def test_holm_against_its_definition():
    p_values = np.array([0.01, 0.04, 0.03, 0.005, np.nan, 0.2])
    # 5 tested; at 0.01 the smallest, 0.005, is above 0.01 / 5: nothing is rejected
    assert not holm_rejections(p_values, 0.01).any()
    # at 0.03: 0.005 <= 0.03 / 5, then 0.01 > 0.03 / 4 stops the procedure
    assert holm_rejections(p_values, 0.03).tolist() == [False, False, False, True, False, False]
    # at 0.1: 0.005 <= 0.02, 0.01 <= 0.025, 0.03 <= 0.0333, 0.04 <= 0.05, then 0.2 > 0.1
    assert holm_rejections(p_values, 0.1).tolist() == [True, True, True, True, False, False]
    assert not holm_rejections(np.array([np.nan, np.nan]), 0.5).any()


def test_holm_controls_the_family_wise_error_on_null_p_values():
    rng = np.random.default_rng(11)
    false_alarms = sum(holm_rejections(rng.uniform(size=144), 0.05).any() for _ in range(4000))
    assert false_alarms / 4000 == pytest.approx(0.05, abs=0.012)
