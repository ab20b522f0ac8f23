"""The raw-value (float32) anchor path agrees with the float64 weights it replaces."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

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


@pytest.mark.parametrize("width", [1, 2, 3, 4, 7, 8, 1023, 4095, 4096])
def test_anchor_weights_are_those_of_np_median_bit_for_bit(width):
    rng = np.random.default_rng(width)
    noise = rng.normal(size=(20, width))
    tail = rng.exponential(size=noise.shape) ** 8
    for rows in (noise, np.round(noise * 2), noise * 1e300, noise * 1e-310, tail):
        with np.errstate(over="ignore"):
            weights = rows - rows.min(axis=1, keepdims=True)
            expected = np.where(weights >= np.median(weights, axis=1, keepdims=True), weights, 0.0)
            actual = normalized_weights(rows).weights
        degenerate = ~np.isfinite(expected.sum(axis=1)) | (expected.sum(axis=1) <= 0)
        assert actual[~degenerate].tobytes() == expected[~degenerate].tobytes()


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


@pytest.mark.parametrize("include_peak", [True, False])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_rows_that_are_not_finite_are_uninformative(dtype, include_peak):
    heatmaps = np.random.default_rng(0).random((4, 32, 32)).astype(dtype)
    heatmaps[0, 1, 1], heatmaps[1, 2, 2], heatmaps[2, 3, 3] = np.nan, np.inf, -np.inf
    statistics = heatmap_statistics(heatmaps, include_peak=include_peak)
    np.testing.assert_array_equal(statistics.uninformative, [True, True, True, False])
    np.testing.assert_array_equal(statistics.mean[:3], np.full((3, 2), 16.0))
    finite = heatmap_statistics(heatmaps[3:], include_peak=include_peak)
    assert statistics.covariance[3].tobytes() == finite.covariance[0].tobytes()


def test_the_peak_is_the_first_maximum_of_the_weights_not_of_the_raw_values():
    heatmap = np.full((1, 64, 64), -1e6)
    heatmap[0, 1, 36], heatmap[0, 46, 56] = 1.0, 1.0 + 2**-40  # distinct raw values, one weight
    assert heatmap.argmax() == 46 * 64 + 56
    statistics = heatmap_statistics(heatmap)
    np.testing.assert_array_equal(statistics.peak_location, [[36.5, 1.5]])


@st.composite
def adversarial_heatmaps(draw):
    """Batches (N, H, W), float32 or float64 without NaN, and a top K, k = 1 and k = H*W included."""
    dtype = draw(st.sampled_from([np.float32, np.float64]))
    height, width = draw(st.sampled_from([(1, 2), (3, 5), (24, 24), (32, 32), (64, 64), (48, 80)]))
    kind = draw(st.sampled_from(["noise", "blob", "levels", "zeros", "constant", "merged", "generated"]))
    n = draw(st.integers(1, 4))
    if kind == "generated" and height * width <= 600:
        elements = st.floats(-1e3, 1e3, allow_nan=False, width=np.dtype(dtype).itemsize * 8)
        heatmaps = draw(hnp.arrays(dtype, (n, height, width), elements=elements))
    else:
        rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
        noise = rng.normal(size=(n, height, width))
        y, x = np.mgrid[:height, :width]
        center = rng.uniform(0, max(height, width), (n, 2, 1, 1))
        blob = np.exp(-((x - center[:, 0]) ** 2 + (y - center[:, 1]) ** 2) / rng.uniform(2, 30))
        heatmaps = {
            "noise": noise,
            "blob": blob + 0.05 * noise,
            "levels": np.round(blob * 6) / 3,
            "zeros": np.where(blob > rng.uniform(0.05, 0.9), blob, 0.0),
            "constant": np.full_like(noise, rng.normal()),
            "merged": np.where(blob > rng.uniform(0.05, 0.5), blob, -1e30),  # weights merge by rounding
            "generated": noise,
        }[kind].astype(dtype)
    size = height * width
    k = draw(st.one_of(st.just(1), st.just(size), st.integers(1, max(1, size // 2)), st.integers(1, size)))
    return heatmaps, k


def _same_bits(actual: np.ndarray, expected: np.ndarray) -> None:
    assert actual.dtype == expected.dtype and actual.shape == expected.shape
    assert actual.tobytes() == expected.tobytes(), f"{actual!r} != {expected!r}"


@settings(max_examples=250, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(case=adversarial_heatmaps())
def test_the_spread_read_off_the_raw_values_is_bit_for_bit_the_float64_one(case):
    heatmaps, k = case
    raw = heatmap_statistics(heatmaps, top_k=k, include_peak=False)  # the raw top-K path where it applies
    exact = heatmap_statistics(heatmaps, top_k=k)  # peak forces float64 weights for every row
    for name in ("uninformative", "mean", "covariance"):
        _same_bits(getattr(raw, name), getattr(exact, name))


def _reference(kind, heatmaps, keypoints):
    return [reference.score(kind, h.astype(np.float64), k) for h, k in zip(heatmaps, keypoints, strict=True)]
