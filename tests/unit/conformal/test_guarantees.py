import numpy as np
import pytest
from scipy import stats

from service.conformal import beta_cdf, binomial_cdf, calibrate, coverage_guarantee, pac_rank


@pytest.mark.parametrize("n", [1, 2, 5, 19, 50, 200, 1000, 5000])
def test_beta_cdf_matches_scipy(n):
    ts = np.unique(np.linspace(1, n, 12).astype(int))
    for t in ts:
        a, b = n + 1 - t, t
        for x in (1e-3, 0.05, 0.5, 0.8, 0.9, 0.95, 0.999):
            expected = stats.beta(a, b).cdf(x)
            assert beta_cdf(x, a, b) == pytest.approx(expected, rel=1e-10, abs=1e-300)


def test_beta_cdf_large_n_is_stable():
    n = 1_000_000
    for t in (1, 1_000, 100_000, 500_000):
        for x in (0.85, 0.9, 0.95):
            value = beta_cdf(x, n + 1 - t, t)
            assert 0.0 <= value <= 1.0
            assert value == pytest.approx(stats.beta(n + 1 - t, t).cdf(x), rel=1e-6, abs=1e-300)


def test_binomial_cdf_edges():
    assert binomial_cdf(-1, 10, 0.3) == 0.0
    assert binomial_cdf(10, 10, 0.3) == 1.0
    assert binomial_cdf(3, 10, 0.0) == 1.0
    assert binomial_cdf(3, 10, 1.0) == 0.0


@pytest.mark.parametrize(
    ("n", "epsilon", "delta"), [(200, 0.1, 0.1), (200, 0.05, 0.05), (1000, 0.2, 0.01), (5, 0.1, 0.1)]
)
def test_pac_rank_is_the_largest_admissible(n, epsilon, delta):
    t = pac_rank(n, epsilon, delta)

    def failure(rank):
        return 0.0 if rank == 0 else stats.beta(n + 1 - rank, rank).cdf(1 - epsilon)

    assert failure(t) <= delta
    assert t == n or failure(t + 1) > delta
    guarantee = coverage_guarantee(n, epsilon, delta)
    assert guarantee.t == t and guarantee.pac_failure_probability <= delta
    assert guarantee.pac_level == pytest.approx(1 - delta)


def test_marginal_guarantee_fields():
    guarantee = calibrate(np.random.default_rng(0).random(200), 0.1).guarantee
    assert (guarantee.n, guarantee.t) == (200, 20)
    assert (guarantee.beta_a, guarantee.beta_b) == (181, 20)
    assert guarantee.marginal_lower == pytest.approx(0.9)
    assert guarantee.marginal_upper == pytest.approx(0.9 + 1 / 201)
    assert guarantee.marginal_lower <= guarantee.marginal_coverage <= guarantee.marginal_upper
    assert guarantee.pac_level is None
    assert guarantee.as_dict()["beta_a"] == 181
