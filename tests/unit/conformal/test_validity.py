"""Validity by simulation: conditional coverage ~ Beta(n+1-t, t) (eq. 5) and the PAC option.

Exchangeable data: i.i.d. anisotropic blob heatmaps whose label is drawn from
the blob itself. A large pool plays the population; each split draws n = 200
calibration samples without replacement and measures coverage on the rest.
"""

import numpy as np
import pytest
from scipy import stats

from service.conformal import (
    calibrate,
    conformal_rank,
    contains,
    nonconformity_scores,
    prediction_sets,
)

from .synthetic import gaussian_blobs

POOL, N_CALIBRATION, SPLITS = 20_000, 200, 500


def _pool(kind: str, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    scores = []
    for _ in range(POOL // 2_000):
        heatmaps, centers = gaussian_blobs(rng, 2_000, size=24, noise=0.01)
        labels = centers + rng.normal(0, 1.5, centers.shape)
        scores.append(nonconformity_scores(kind, heatmaps, labels))
    return np.concatenate(scores)


@pytest.fixture(scope="module")
def pools():
    return {kind: _pool(kind, seed) for seed, kind in enumerate(("peak", "var", "cov"))}


def _split_coverages(scores, epsilon, delta=None, seed=0):
    rng = np.random.default_rng(seed)
    coverages = np.empty(SPLITS)
    for i in range(SPLITS):
        order = rng.permutation(scores.size)
        calibration, test = scores[order[:N_CALIBRATION]], scores[order[N_CALIBRATION:]]
        threshold = calibrate(calibration, epsilon, delta).threshold
        coverages[i] = np.mean(test <= threshold)
    return coverages


@pytest.mark.slow
@pytest.mark.parametrize("epsilon", [0.05, 0.1, 0.2])
@pytest.mark.parametrize("kind", ["peak", "var", "cov"])
def test_coverage_follows_beta(pools, kind, epsilon):
    coverages = _split_coverages(pools[kind], epsilon, seed=2024)
    t = conformal_rank(N_CALIBRATION, epsilon)
    result = stats.kstest(coverages, stats.beta(N_CALIBRATION + 1 - t, t).cdf)
    assert result.pvalue > 0.01
    assert coverages.mean() >= 1 - epsilon - 3 * coverages.std() / np.sqrt(SPLITS)


@pytest.mark.slow
@pytest.mark.parametrize("delta", [0.05, 0.1])
def test_pac_coverage_holds_in_at_least_1_minus_delta_of_splits(pools, delta):
    epsilon = 0.1
    coverages = _split_coverages(pools["cov"], epsilon, delta=delta, seed=99)
    assert np.mean(coverages >= 1 - epsilon) >= 1 - delta


def test_empirical_coverage_through_the_sets():
    rng = np.random.default_rng(5)
    heatmaps, centers = gaussian_blobs(rng, 1_200, size=32, noise=0.01)
    labels = centers + rng.normal(0, 1.5, centers.shape)
    for kind in ("peak", "var", "cov"):
        threshold = calibrate(nonconformity_scores(kind, heatmaps[:200], labels[:200]), 0.1).threshold
        set_centers, shapes = prediction_sets(kind, heatmaps[200:], threshold)
        coverage = contains(labels[200:], set_centers, shapes).mean()
        assert 0.85 <= coverage <= 0.97
