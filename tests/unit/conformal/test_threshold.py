import math

import numpy as np
import pytest

from service.conformal import (
    calibrate,
    calibrate_columns,
    column_thresholds,
    conformal_rank,
    conformal_threshold,
    object_scores,
    threshold_for_rank,
)


def test_small_n_is_unbounded():
    scores = np.array([0.3, 0.1, 0.5, 0.2, 0.4])
    assert conformal_threshold(scores, 0.1) == math.inf
    assert calibrate(scores, 0.1).guarantee.unbounded


def test_threshold_is_the_t_th_largest():
    scores = np.arange(1.0, 10.0)  # n = 9, eps = 0.1 -> t = 1 -> the largest
    assert conformal_threshold(scores, 0.1) == 9.0
    assert conformal_threshold(np.arange(1.0, 20.0), 0.1) == 18.0  # n = 19 -> t = 2


@pytest.mark.parametrize(
    ("n", "epsilon", "t"), [(9, 0.1, 1), (99, 0.29, 29), (199, 0.05, 10), (59, 0.7, 42), (4, 0.2, 1)]
)
def test_rank_is_exact_for_decimal_epsilons(n, epsilon, t):
    assert conformal_rank(n, epsilon) == t


def test_rank_with_numpy_scalar():
    assert conformal_rank(9, np.float64(0.1)) == 1


def test_nan_scores_are_ignored():
    scores = np.array([np.nan, 5.0, 1.0, np.nan, 3.0] + [0.0] * 6)
    assert conformal_threshold(scores, 0.1) == 5.0  # n = 9, not 11
    assert calibrate(scores, 0.1).guarantee.n == 9


@pytest.mark.parametrize("epsilon", [0.0, 1.0, -0.1, 1.5, float("nan")])
def test_invalid_epsilon(epsilon):
    with pytest.raises(ValueError):
        conformal_threshold(np.ones(10), epsilon)


def test_column_thresholds_match_per_column():
    rng = np.random.default_rng(0)
    matrix = rng.random((150, 12))
    matrix[rng.random(matrix.shape) < 0.3] = np.nan
    thresholds, guarantees = calibrate_columns(matrix, 0.1)
    for column, threshold, guarantee in zip(matrix.T, thresholds, guarantees, strict=True):
        assert threshold == conformal_threshold(column, 0.1)
        assert guarantee.n == np.count_nonzero(~np.isnan(column))
    ranks = np.zeros(12, dtype=int)
    assert np.all(column_thresholds(matrix, ranks) == np.inf)


def test_object_scores_need_every_keypoint():
    matrix = np.array([[1.0, 3.0, 2.0], [1.0, np.nan, 9.0]])
    result = object_scores(matrix)
    assert result[0] == 3.0 and np.isnan(result[1])


def test_threshold_for_rank_bounds():
    with pytest.raises(ValueError):
        threshold_for_rank(np.ones(3), 4)
    assert threshold_for_rank(np.ones(3), 0) == math.inf
