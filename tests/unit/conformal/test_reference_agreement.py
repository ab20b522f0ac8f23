"""The vectorized module agrees with the plain per-heatmap reference to 1e-9."""

import numpy as np
import pytest

from service.conformal import nonconformity_scores, point_estimates, prediction_sets

from . import reference
from .synthetic import gaussian_blobs, mixed_heatmaps

KINDS = ("peak", "var", "cov")


@pytest.fixture(scope="module")
def batch():
    rng = np.random.default_rng(20240601)
    heatmaps = mixed_heatmaps(rng, 300)
    keypoints = rng.uniform(0, 64, (300, 2))
    return heatmaps, keypoints


@pytest.mark.parametrize("mode", ["anchor", "relu", "softmax"])
@pytest.mark.parametrize("kind", KINDS)
def test_scores_match_reference(batch, kind, mode):
    heatmaps, keypoints = batch
    expected = [reference.score(kind, h, k, mode) for h, k in zip(heatmaps, keypoints, strict=True)]
    actual = nonconformity_scores(kind, heatmaps, keypoints, normalization=mode)
    np.testing.assert_allclose(actual, expected, rtol=1e-9, atol=0)


@pytest.mark.parametrize("kind", KINDS)
def test_sets_match_reference(batch, kind):
    heatmaps, _ = batch
    thresholds = np.random.default_rng(7).uniform(0.01, 3.0, len(heatmaps))
    centers, shapes = prediction_sets(kind, heatmaps, thresholds)
    for i, (heatmap, threshold) in enumerate(zip(heatmaps, thresholds, strict=True)):
        center, shape = reference.region(kind, heatmap, threshold)
        np.testing.assert_allclose(centers[i], center, rtol=1e-9)
        np.testing.assert_allclose(shapes[i], shape, rtol=1e-9, atol=1e-12 * np.abs(shape).max())


@pytest.mark.parametrize("top_k", [1, 5, 100, 2048, 4096])
def test_top_k_values_match_reference(top_k):
    rng = np.random.default_rng(top_k)
    heatmaps, _ = gaussian_blobs(rng, 40, noise=0.02)
    keypoints = rng.uniform(0, 64, (40, 2))
    expected = [reference.score("cov", h, k, k=top_k) for h, k in zip(heatmaps, keypoints, strict=True)]
    actual = nonconformity_scores("cov", heatmaps, keypoints, top_k=top_k)
    np.testing.assert_allclose(actual, expected, rtol=1e-9)


def test_quantized_heatmaps_with_ties_follow_row_major_tie_break():
    rng = np.random.default_rng(3)
    blobs, _ = gaussian_blobs(rng, 50, size=48)
    heatmaps = np.round(blobs * 12)  # many exact ties, also at the 100th value
    keypoints = rng.uniform(0, 48, (50, 2))
    for kind in KINDS:
        expected = [reference.score(kind, h, k) for h, k in zip(heatmaps, keypoints, strict=True)]
        np.testing.assert_allclose(nonconformity_scores(kind, heatmaps, keypoints), expected, rtol=1e-9)


def test_point_estimates_are_the_set_centres(batch):
    heatmaps, _ = batch
    for kind in KINDS:
        centers, _ = prediction_sets(kind, heatmaps, 1.0)
        np.testing.assert_array_equal(point_estimates(kind, heatmaps), centers)


def test_non_square_heatmaps():
    rng = np.random.default_rng(11)
    heatmaps = rng.random((20, 24, 40))
    keypoints = rng.uniform(0, 24, (20, 2))
    for kind in KINDS:
        expected = [reference.score(kind, h, k) for h, k in zip(heatmaps, keypoints, strict=True)]
        np.testing.assert_allclose(nonconformity_scores(kind, heatmaps, keypoints), expected, rtol=1e-9)
