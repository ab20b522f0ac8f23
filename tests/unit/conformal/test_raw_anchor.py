"""The raw-value (float32) anchor path agrees with the float64 weights it replaces."""

import numpy as np
import pytest

from service.conformal import heatmap_statistics, nonconformity_scores
from service.conformal.anchor import isolated, raw_top_k
from service.conformal.normalization import normalized_weights
from service.conformal.selection import top_k_indices

from . import reference
from .synthetic import gaussian_blobs, mixed_heatmaps

KINDS = ("peak", "var", "cov")


@pytest.fixture(scope="module")
def float32_batch():
    rng = np.random.default_rng(5)
    heatmaps = mixed_heatmaps(rng, 120).astype(np.float32)
    return heatmaps, rng.uniform(0, 64, (120, 2))


@pytest.mark.parametrize("kind", KINDS)
def test_float32_input_scores_equal_float64_input_of_the_same_values(float32_batch, kind):
    heatmaps, keypoints = float32_batch
    from_float32 = nonconformity_scores(kind, heatmaps, keypoints)
    from_float64 = nonconformity_scores(kind, heatmaps.astype(np.float64), keypoints)
    np.testing.assert_allclose(from_float32, from_float64, rtol=1e-12, atol=0)


@pytest.mark.parametrize("kind", KINDS)
def test_float32_input_matches_the_reference(float32_batch, kind):
    heatmaps, keypoints = float32_batch
    expected = _reference(kind, heatmaps, keypoints)
    np.testing.assert_allclose(nonconformity_scores(kind, heatmaps, keypoints), expected, rtol=1e-9)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_top_k_on_raw_values_equals_top_k_on_weights_with_ties(dtype):
    rng = np.random.default_rng(9)
    blobs, _ = gaussian_blobs(rng, 60, size=64, noise=0.01)
    raw = (np.round(blobs * 40) / 7).astype(dtype).reshape(60, -1)  # many exact ties
    minimum = raw.min(axis=1).astype(np.float64)
    indices, weights, exact = raw_top_k(raw, 100, minimum)
    assert exact.all() or dtype == np.float64  # float64 neighbours may merge: conservative flag
    expected = top_k_indices(normalized_weights(raw.astype(np.float64), skip_anchor_median=True).weights, 100)
    np.testing.assert_array_equal(np.sort(indices, axis=1)[exact], np.sort(expected, axis=1)[exact])
    selected = np.take_along_axis(raw, indices, 1).astype(np.float64)
    np.testing.assert_array_equal(weights, selected - minimum[:, None])


def test_isolated_detects_raw_values_merged_by_rounding():
    values = np.array([1e-30, 1.0], dtype=np.float32)
    minimum = np.array([-1.0, -1.0])  # 1e-30 - (-1) rounds to 1.0 in float64, like 0 and its neighbours
    np.testing.assert_array_equal(isolated(values, minimum), [False, True])


@pytest.mark.parametrize("kind", KINDS)
def test_the_numpy_path_matches_the_reference(float32_batch, kind):
    heatmaps, keypoints = float32_batch
    expected = _reference(kind, heatmaps, keypoints)
    np.testing.assert_allclose(nonconformity_scores(kind, heatmaps, keypoints), expected, rtol=1e-9)


def test_rows_that_fail_the_shortcuts_take_the_exact_path():
    rng = np.random.default_rng(4)
    heatmaps, _ = gaussian_blobs(rng, 12, size=64, noise=0.02)
    heatmaps[0] = 0.0
    heatmaps[0, 10:30, 10:30] = 1.0  # the median value tied many times
    heatmaps[1] += 1e6  # the normalizer sum fails the rounding bound
    heatmaps[2, ::2] = 5.0  # half the map tied at the maximum
    heatmaps[3] = np.where(heatmaps[3] > 0.5, heatmaps[3], -1e30)  # weights merge by rounding
    keypoints = rng.uniform(0, 64, (12, 2))
    for dtype in (np.float32, np.float64):
        values = heatmaps.astype(dtype)
        for kind in KINDS:
            expected = _reference(kind, values, keypoints)
            np.testing.assert_allclose(nonconformity_scores(kind, values, keypoints), expected, rtol=1e-9)


def test_non_finite_float32_rows_are_uninformative():
    heatmaps = np.random.default_rng(0).random((3, 32, 32)).astype(np.float32)
    heatmaps[0, 1, 1], heatmaps[1, 2, 2] = np.nan, np.inf
    statistics = heatmap_statistics(heatmaps)
    np.testing.assert_array_equal(statistics.uninformative, [True, True, False])


def _reference(kind, heatmaps, keypoints):
    return [reference.score(kind, h.astype(np.float64), k) for h, k in zip(heatmaps, keypoints, strict=True)]
