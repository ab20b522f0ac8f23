"""Degenerate heatmaps give finite, conservative (large, centred) answers, never NaN."""

import math

import numpy as np
import pytest

from service.conformal import (
    ellipse_axes,
    heatmap_statistics,
    nonconformity_scores,
    normalize_heatmaps,
    prediction_sets,
)

SIZE = 32


def _degenerate_batch():
    spike = np.zeros((SIZE, SIZE))
    spike[5, 7] = 1.0
    line = np.zeros((SIZE, SIZE))
    line[10, :] = 1.0
    return {
        "constant": np.full((SIZE, SIZE), 3.0),
        "zeros": np.zeros((SIZE, SIZE)),
        "nan": np.where(np.eye(SIZE) > 0, np.nan, 1.0),
        "inf": np.where(np.eye(SIZE) > 0, np.inf, 1.0),
        "huge": np.full((SIZE, SIZE), 1e308) * np.linspace(0.5, 1, SIZE),
        "spike": spike,
        "line": line,
    }


@pytest.mark.parametrize("mode", ["anchor", "relu", "softmax"])
def test_normalized_maps_are_probabilities(mode):
    maps = normalize_heatmaps(np.stack(list(_degenerate_batch().values())), mode)
    assert np.all(np.isfinite(maps)) and np.all(maps >= 0)
    np.testing.assert_allclose(maps.sum(axis=(1, 2)), 1.0)


@pytest.mark.parametrize("mode", ["anchor", "relu", "softmax"])
@pytest.mark.parametrize("kind", ["peak", "var", "cov"])
def test_scores_and_sets_are_finite(kind, mode):
    heatmaps = np.stack(list(_degenerate_batch().values()))
    keypoints = np.full((len(heatmaps), 2), 3.0)
    assert np.all(np.isfinite(nonconformity_scores(kind, heatmaps, keypoints, normalization=mode)))
    centers, shapes = prediction_sets(kind, heatmaps, 1.0, normalization=mode)
    assert np.all(np.isfinite(centers)) and np.all(np.isfinite(shapes))


@pytest.mark.parametrize("kind", ["peak", "var", "cov"])
def test_uninformative_maps_give_centred_sets_as_large_as_the_map(kind):
    batch = _degenerate_batch()
    heatmaps = np.stack([batch["constant"], batch["zeros"], batch["nan"], batch["inf"]])
    centers, shapes = prediction_sets(kind, heatmaps, 1.0)
    np.testing.assert_array_equal(centers, np.full((4, 2), SIZE / 2))
    semi_minor, _, _ = ellipse_axes(shapes)
    expected_minimum = {"peak": SIZE * SIZE, "var": SIZE / math.sqrt(6), "cov": SIZE / math.sqrt(12)}
    assert np.all(semi_minor >= expected_minimum[kind] * (1 - 1e-12))


def test_singular_covariance_is_regularized_to_a_pixel():
    batch = _degenerate_batch()
    statistics = heatmap_statistics(np.stack([batch["spike"], batch["line"]]))
    eigenvalues = np.linalg.eigvalsh(statistics.regularized_covariance)
    np.testing.assert_allclose(eigenvalues[:, 0], 1 / 12)
    assert np.all(statistics.regularized_variance >= 1 / 6)
    scores = nonconformity_scores("cov", np.stack([batch["spike"]]), np.array([[7.5, 5.5]]))
    assert scores[0] == 0.0


def test_unbounded_threshold_gives_zero_shapes():
    heatmaps = np.random.default_rng(0).random((3, SIZE, SIZE))
    for kind in ("peak", "var", "cov"):
        _, shapes = prediction_sets(kind, heatmaps, math.inf)
        assert np.all(shapes == 0)


def test_bad_arguments_raise_value_errors():
    heatmaps = np.zeros((2, 4, 4))
    with pytest.raises(ValueError):
        nonconformity_scores("bogus", heatmaps, np.zeros((2, 2)))
    with pytest.raises(ValueError):
        nonconformity_scores("cov", heatmaps, np.zeros((3, 2)))
    with pytest.raises(ValueError):
        prediction_sets("cov", heatmaps, -1.0)
    with pytest.raises(ValueError):
        normalize_heatmaps(heatmaps, "softmax", temperature=0.0)
    with pytest.raises(ValueError):
        normalize_heatmaps(heatmaps, "bogus")
