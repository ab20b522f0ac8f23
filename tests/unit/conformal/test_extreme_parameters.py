"""Every epsilon and delta in (0, 1), subnormals and neighbours of 0 and 1 included, gets an answer.

Issue 12 item 5: epsilon <= 5.5e-17 with a delta crashed (1 - eps rounded to 1, log1p(-1)).
The reference is scipy's cephes ``bdtr`` / ``bdtrc`` (the binomial lower tail and its
complement) and ``betainc``, each used where it is reliable: below the normal range
(about 1e-300) it underflows, and ``bdtr`` computes 1 - p, so its small values are only
compared where ``bdtrc`` does not take over.
"""

from __future__ import annotations

import itertools
import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from scipy import special

from service.conformal import (
    CoverageGuarantee,
    beta_cdf,
    binomial_cdf,
    calibrate,
    calibrate_columns,
    conformal_rank,
    coverage_guarantee,
    pac_rank,
)

EDGES = (5e-324, 2.2e-308, 5.5e-17, 1e-16, 1 - 2**-53, 0.5)
UNIT = st.floats(min_value=0, max_value=1, exclude_min=True, exclude_max=True, allow_subnormal=True)
RELIABLE = 1e-290  # scipy's tails below this have lost digits or underflowed
RELATIVE = 1e-9
SETTINGS = settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def check_guarantee(guarantee: CoverageGuarantee, n: int, epsilon: float, delta: float | None) -> None:
    """The invariants of one answer: rank in range, finite bounds in [0, 1], PAC level met."""
    assert (guarantee.n, guarantee.epsilon, guarantee.delta) == (n, epsilon, delta)
    assert 0 <= guarantee.t <= n
    assert guarantee.unbounded == (guarantee.t == 0)
    assert (guarantee.beta_a, guarantee.beta_b) == (n + 1 - guarantee.t, guarantee.t)
    for name, value in guarantee.as_dict().items():
        if isinstance(value, float):
            assert math.isfinite(value) and 0.0 <= value <= 1.0, (name, value)
    assert guarantee.marginal_lower <= guarantee.marginal_coverage <= guarantee.marginal_upper
    if delta is None:
        assert guarantee.t == conformal_rank(n, epsilon)
    else:
        assert guarantee.t == min(conformal_rank(n, epsilon), pac_rank(n, epsilon, delta))
        assert guarantee.pac_failure_probability <= delta


def scipy_failure_within(n: int, t: int, epsilon: float, delta: float, slack: float) -> bool | None:
    """Whether scipy finds P(Bin(n, eps) <= t-1) <= delta * (1 + slack); None where it cannot tell.

    Near 1 the complement is compared (bdtrc is exact there), near 0 the tail itself.
    """
    if t == 0:
        return True
    if delta > 0.5:
        survival = special.bdtrc(t - 1, n, epsilon)
        return bool(survival >= (1 - delta) * (1 - slack))
    failure = special.bdtr(t - 1, n, epsilon)
    if failure < RELIABLE or delta < RELIABLE:
        return None
    return bool(failure <= delta * (1 + slack))


@SETTINGS
@given(n=st.integers(0, 2000), epsilon=UNIT, delta=st.none() | UNIT)
@example(n=400, epsilon=5.5e-17, delta=0.1)  # the crash of issue 12
@example(n=400, epsilon=5e-324, delta=5e-324)
@example(n=400, epsilon=0.1, delta=1 - 2**-53)
@example(n=400, epsilon=1 - 2**-53, delta=5e-324)
def test_every_epsilon_and_delta_gets_a_guarantee(n: int, epsilon: float, delta: float | None) -> None:
    check_guarantee(coverage_guarantee(n, epsilon, delta), n, epsilon, delta)


@SETTINGS
@given(n=st.integers(1, 2000), epsilon=UNIT, delta=UNIT)
@example(n=400, epsilon=0.1, delta=1 - 2**-53)
@example(n=10_000, epsilon=0.1, delta=2.2e-308)
@example(n=400, epsilon=1 - 2**-53, delta=0.5)
@example(n=2000, epsilon=1e-16, delta=1 - 2**-53)
def test_pac_rank_is_the_largest_admissible_by_scipy(n: int, epsilon: float, delta: float) -> None:
    t = pac_rank(n, epsilon, delta)
    assert scipy_failure_within(n, t, epsilon, delta, RELATIVE) is not False
    if t < n:
        assert scipy_failure_within(n, t + 1, epsilon, delta, -RELATIVE) is not True


def test_near_one_delta_is_decided_on_the_complement() -> None:
    """delta = 1 - 2**-53: t must keep P(Bin(n, eps) > t-1) >= 2**-53, which 1 - P(<= t-1) cannot see."""
    n, epsilon, delta = 400, 0.1, 1 - 2**-53
    t = pac_rank(n, epsilon, delta)
    assert special.bdtrc(t - 1, n, epsilon) >= 2**-53 > special.bdtrc(t, n, epsilon)


def test_a_large_delta_keeps_the_marginal_guarantee() -> None:
    """n = 98, eps = 0.01: the marginal set is unbounded (t = 0); PAC at delta = 0.38 alone says t = 1,
    which would cover only 1 - 1/99 < 0.99 marginally. A PAC request never makes a set smaller."""
    assert conformal_rank(98, 0.01) == 0 and pac_rank(98, 0.01, 0.38) == 1
    guarantee = coverage_guarantee(98, 0.01, 0.38)
    assert guarantee.t == 0 and guarantee.marginal_coverage >= guarantee.marginal_lower


def test_subnormal_delta_is_decided_in_log_space() -> None:
    """Tails near 5e-324 have lost their digits in floating point (scipy's included): exactly."""
    n, epsilon, delta = 2000, 0.5, 5e-324
    t = pac_rank(n, epsilon, delta)
    assert t > 0 and coverage_guarantee(n, epsilon, delta).pac_failure_probability == 0.0
    assert exact_cdf(t - 1, n, epsilon) <= Fraction(delta) < exact_cdf(t, n, epsilon)


def exact_cdf(m: int, n: int, p: float) -> Fraction:
    """P(Binomial(n, p) <= m) in rational arithmetic, for the float p exactly."""
    a, d = Fraction(p).as_integer_ratio()
    return Fraction(sum(math.comb(n, j) * a**j * (d - a) ** (n - j) for j in range(m + 1)), d**n)


def exactly_admissible(failure: Fraction, delta: float, slack: float) -> bool:
    """failure <= delta, up to a relative ``slack`` on the smaller of delta and 1 - delta."""
    bound = Fraction(delta)
    if bound <= Fraction(1, 2):
        return failure <= bound * (1 + Fraction(slack))
    return 1 - failure >= (1 - bound) * (1 - Fraction(slack))


@SETTINGS
@given(n=st.integers(1, 80), epsilon=UNIT, delta=UNIT)
@example(n=80, epsilon=5e-324, delta=1 - 2**-53)
@example(n=80, epsilon=1 - 2**-53, delta=5e-324)
@example(n=80, epsilon=0.5, delta=2.2e-308)
@example(n=80, epsilon=1e-16, delta=1e-16)
def test_pac_rank_is_the_largest_admissible_exactly(n: int, epsilon: float, delta: float) -> None:
    """Rational arithmetic is the reference where floating point (scipy's too) underflows or rounds."""
    t = pac_rank(n, epsilon, delta)
    assert t == 0 or exactly_admissible(exact_cdf(t - 1, n, epsilon), delta, RELATIVE)
    assert t == n or not exactly_admissible(exact_cdf(t, n, epsilon), delta, -RELATIVE)


@SETTINGS
@given(m=st.integers(-1, 3000), n=st.integers(1, 3000), p=UNIT)
@example(m=0, n=10, p=5e-324)
@example(m=9, n=10, p=1 - 2**-53)
@example(m=3, n=400, p=5.5e-17)
def test_binomial_cdf_matches_scipy(m: int, n: int, p: float) -> None:
    value = binomial_cdf(m, n, p)
    assert 0.0 <= value <= 1.0
    if m < 0 or m >= n:
        assert value == (0.0 if m < 0 else 1.0)
        return
    lower, upper = special.bdtr(m, n, p), special.bdtrc(m, n, p)
    if lower > 0.5:
        assert 1.0 - value == pytest.approx(upper, rel=RELATIVE, abs=1e-15)
    elif lower >= RELIABLE:
        assert value == pytest.approx(lower, rel=RELATIVE)


@SETTINGS
@given(x=UNIT, a=st.integers(1, 2000), b=st.integers(1, 2000))
@example(x=1e-20, a=3, b=4)
@example(x=5e-324, a=1, b=1)
@example(x=1 - 2**-53, a=5, b=2)
def test_beta_cdf_matches_scipy(x: float, a: int, b: int) -> None:
    value = beta_cdf(x, a, b)
    assert 0.0 <= value <= 1.0
    expected = special.betainc(a, b, x)
    if expected > 0.5:
        complement = special.betainc(b, a, 1.0 - x) if x >= 0.5 else 1.0 - expected
        assert 1.0 - value == pytest.approx(complement, rel=RELATIVE, abs=1e-15)
    elif expected >= RELIABLE:
        assert value == pytest.approx(expected, rel=RELATIVE)


@SETTINGS
@given(
    scores=st.lists(st.floats(0, 1e6) | st.just(math.nan), max_size=60),
    epsilon=UNIT,
    delta=st.none() | UNIT,
)
def test_calibrate_answers_for_every_epsilon_and_delta(
    scores: list[float], epsilon: float, delta: float | None
) -> None:
    array = np.array(scores, dtype=np.float64)
    labeled = array[~np.isnan(array)]
    calibration = calibrate(array, epsilon, delta)
    check_guarantee(calibration.guarantee, labeled.size, epsilon, delta)
    if calibration.guarantee.unbounded:
        assert calibration.threshold == math.inf
    else:
        assert calibration.threshold in labeled
        assert np.count_nonzero(labeled > calibration.threshold) < calibration.guarantee.t


@SETTINGS
@given(
    seed=st.integers(0, 2**32 - 1),
    shape=st.tuples(st.integers(0, 50), st.integers(1, 6)),
    epsilon=UNIT,
    delta=st.none() | UNIT,
)
def test_calibrate_columns_answers_for_every_epsilon_and_delta(
    seed: int, shape: tuple[int, int], epsilon: float, delta: float | None
) -> None:
    rng = np.random.default_rng(seed)
    matrix = rng.exponential(size=shape)
    matrix[rng.random(shape) < 0.3] = np.nan
    thresholds, guarantees = calibrate_columns(matrix, epsilon, delta)
    assert thresholds.shape == (shape[1],) and len(guarantees) == shape[1]
    for column, (threshold, guarantee) in enumerate(zip(thresholds, guarantees, strict=True)):
        check_guarantee(guarantee, int(np.count_nonzero(~np.isnan(matrix[:, column]))), epsilon, delta)
        assert (threshold == math.inf) == guarantee.unbounded
        assert guarantee.unbounded or np.isfinite(threshold)


@pytest.mark.parametrize(("epsilon", "delta"), itertools.product(EDGES, (None, *EDGES)))
@pytest.mark.parametrize("n", [0, 1, 19, 400, 100_000])
def test_edge_values(n: int, epsilon: float, delta: float | None) -> None:
    check_guarantee(coverage_guarantee(n, epsilon, delta), n, epsilon, delta)


@pytest.mark.parametrize(
    ("epsilon", "delta"), [(0.5, 0.1), (1e-3, 1e-3), (5.5e-17, 0.5), (1 - 2**-53, 1e-300)]
)
def test_large_n(epsilon: float, delta: float) -> None:
    n = 10_000_000
    guarantee = coverage_guarantee(n, epsilon, delta)
    check_guarantee(guarantee, n, epsilon, delta)
    if guarantee.t:
        assert guarantee.pac_failure_probability == pytest.approx(
            special.bdtr(guarantee.t - 1, n, epsilon), rel=1e-6
        )


@pytest.mark.parametrize("value", [0.0, -0.0, 1.0, -5e-324, 1 + 2**-52, math.inf, -math.inf, math.nan])
def test_values_outside_the_open_interval_are_refused(value: float) -> None:
    with pytest.raises(ValueError, match="epsilon must be in"):
        coverage_guarantee(100, value)
    with pytest.raises(ValueError, match="delta must be in"):
        coverage_guarantee(100, 0.1, value)
