"""Mondrian strata: each stratum's coverage, averaged over many calibration draws, lies in
[1 - eps, 1 - eps + 1/(n_g + 1)] (Theorem 1 inside the stratum); bins hold >= min_instances.

Scores are exponential with a scale that depends on the stratum (a caller group) or on a
difficulty signal s ~ U(0, 1), so the coverage of a threshold is known in closed form
(1 - exp(-thr / scale)) and no test sample is needed.
"""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from service.conformal import conformal_rank
from service.conformal.strata import (
    DifficultyBins,
    DifficultySpec,
    fit_difficulty_bins,
    quantile_edges,
    stratum_calibrations,
)

DRAWS = 1500
SLOW = settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _band_check(mean: float, n: int, epsilon: float, spread: float) -> None:
    tolerance = 4 * spread / np.sqrt(DRAWS) + 1e-9
    assert mean >= 1 - epsilon - tolerance, (mean, n, epsilon)
    assert mean <= 1 - epsilon + 1 / (n + 1) + tolerance, (mean, n, epsilon)


@SLOW
@given(
    sizes=st.lists(st.integers(9, 120), min_size=2, max_size=4),
    epsilon=st.sampled_from([0.05, 0.1, 0.2]),
    seed=st.integers(0, 2**32 - 1),
)
def test_group_strata_cover_within_their_band_on_average(sizes, epsilon, seed):
    rng = np.random.default_rng(seed)
    scales = rng.uniform(0.2, 5.0, len(sizes))  # groups differ a lot: pooled would miss some
    strata = np.repeat(np.arange(len(sizes)), sizes)
    coverages = np.empty((DRAWS, len(sizes)))
    for draw in range(DRAWS):
        scores = rng.exponential(scales[strata])
        calibrations = stratum_calibrations(scores, strata, len(sizes), epsilon)
        thresholds = np.array([c.threshold for c in calibrations])
        coverages[draw] = 1 - np.exp(-thresholds / scales)  # inf -> 1: an unbounded set covers
    for g, n in enumerate(sizes):
        if conformal_rank(n, epsilon) == 0:
            assert np.all(coverages[:, g] == 1.0)
            continue
        _band_check(coverages[:, g].mean(), n, epsilon, coverages[:, g].std())


def _signal_scale(s: np.ndarray) -> np.ndarray:
    return 0.3 + 4.0 * s**2  # hard keypoints (large s) have much larger scores


@SLOW
@given(
    n=st.integers(120, 400),
    bins=st.integers(2, 5),
    min_instances=st.sampled_from([20, 30, 50]),
    epsilon=st.sampled_from([0.05, 0.1]),
    seed=st.integers(0, 2**32 - 1),
)
def test_difficulty_bins_cover_within_their_band_on_average(n, bins, min_instances, epsilon, seed):
    rng = np.random.default_rng(seed)
    spec = DifficultySpec(("s",), bins, min_instances)
    grid = (np.arange(4000) + 0.5) / 4000  # s is uniform: bin coverage = mean over the bin's grid points
    per_bin: dict[int, list[float]] = {}
    sizes: dict[int, set[int]] = {}
    for _ in range(DRAWS // 3):
        s = rng.uniform(0, 1, n)
        scores = rng.exponential(_signal_scale(s))
        fitted = fit_difficulty_bins({"s": s}, spec)
        calibrations = stratum_calibrations(scores, fitted.assign({"s": s}), fitted.n_bins, epsilon)
        grid_bins = fitted.assign({"s": grid})
        for b, calibration in enumerate(calibrations):
            inside = grid[grid_bins == b]
            coverage = np.mean(1 - np.exp(-calibration.threshold / _signal_scale(inside)))
            per_bin.setdefault(b, []).append(coverage)
            sizes.setdefault(b, set()).add(calibration.guarantee.n)
    assert min(min(v) for v in sizes.values()) >= min(min_instances, n)
    for b, values in per_bin.items():
        smallest, largest = min(sizes[b]), max(sizes[b])
        mean, spread = float(np.mean(values)), float(np.std(values))
        tolerance = 4 * spread / np.sqrt(len(values)) + 0.01  # + edges fitted on the same draw
        assert mean >= 1 - epsilon - tolerance, (b, mean)
        assert mean <= 1 - epsilon + 1 / (smallest + 1) + tolerance, (b, mean, smallest, largest)


@settings(max_examples=200, deadline=None)
@given(
    values=st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=0, max_size=300),
    bins=st.integers(1, 8),
    min_instances=st.integers(1, 60),
)
def test_every_quantile_bin_holds_at_least_min_instances(values, bins, min_instances):
    values = np.round(np.asarray(values), 1)  # rounding makes ties, which must merge bins
    edges = quantile_edges(values, bins, min_instances)
    assert edges.size <= bins - 1
    assert np.all(np.diff(edges) > 0)
    counts = np.bincount(np.searchsorted(edges, values, side="right"), minlength=edges.size + 1)
    if edges.size:
        assert counts.min() >= min_instances


def test_joint_bins_split_the_second_signal_within_each_bin_of_the_first():
    rng = np.random.default_rng(7)
    features = {"a": rng.uniform(0, 1, 900), "b": rng.uniform(0, 1, 900)}
    fitted = fit_difficulty_bins(features, DifficultySpec(("a", "b"), 3, 50))
    assert fitted.n_bins == 9 and len(fitted.edges) == 2 and all(len(e) == 2 for e in fitted.inner_edges)
    assigned = fitted.assign(features)
    assert np.bincount(assigned).tolist() == list(fitted.counts) == [100] * 9
    low_a, high_a = fitted.ranges(4)["a"]
    inside = assigned == 4
    assert np.all((features["a"][inside] >= low_a) & (features["a"][inside] < high_a))
    assert DifficultyBins.from_dict(fitted.as_dict()) == fitted


def test_too_few_instances_make_one_bin_that_is_the_pooled_stratum():
    values = np.arange(40.0)
    assert quantile_edges(values, 4, 30).size == 0
    fitted = fit_difficulty_bins({"s": values}, DifficultySpec(("s",), 4, 30))
    assert fitted.n_bins == 1 and fitted.counts == (40,)
