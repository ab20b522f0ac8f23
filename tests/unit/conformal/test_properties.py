"""Hypothesis properties: eq. (3) membership, scale invariance, monotone sets."""

import numpy as np
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from service.conformal import contains, nonconformity_scores, prediction_sets

from .synthetic import gaussian_blobs

KINDS = st.sampled_from(["peak", "var", "cov"])
SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@st.composite
def heatmap_batches(draw, max_n: int = 6):
    n = draw(st.integers(1, max_n))
    height, width = draw(st.integers(2, 24)), draw(st.integers(2, 24))
    values = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False, allow_subnormal=False, width=64)
    heatmaps = draw(arrays(np.float64, (n, height, width), elements=values))
    points = draw(arrays(np.float64, (n, 2), elements=st.floats(-5, 30, width=64)))
    return heatmaps, points


@SETTINGS
@given(batch=heatmap_batches(), kind=KINDS, threshold=st.floats(1e-3, 1e3), top_k=st.integers(1, 150))
def test_keypoint_in_set_iff_score_at_most_threshold(batch, kind, threshold, top_k):
    heatmaps, points = batch
    scores = nonconformity_scores(kind, heatmaps, points, top_k=top_k)
    centers, shapes = prediction_sets(kind, heatmaps, threshold, top_k=top_k)
    clear = np.abs(scores - threshold) > 1e-9 * threshold  # rounding decides exact ties
    inside = contains(points, centers, shapes)
    np.testing.assert_array_equal(inside[clear], (scores <= threshold)[clear])


@SETTINGS
@given(
    batch=heatmap_batches(),
    kind=KINDS,
    mode=st.sampled_from(["anchor", "relu"]),
    factor=st.integers(-10, 10).map(lambda exponent: 2.0**exponent),
)
def test_anchor_and_relu_scores_are_scale_invariant(batch, kind, mode, factor):
    """A power of two scales every value, median and difference exactly: any other factor rounds,
    and a value at the median (an average of two) may then fall on the other side of it."""
    heatmaps, points = batch
    scaled_values = np.abs(heatmaps[heatmaps != 0] * factor)
    assume(scaled_values.size == 0 or scaled_values.min() >= 1e-290)  # no underflow to subnormals
    original = nonconformity_scores(kind, heatmaps, points, normalization=mode)
    scaled = nonconformity_scores(kind, heatmaps * factor, points, normalization=mode)
    np.testing.assert_allclose(scaled, original, rtol=1e-7, atol=1e-12)


@SETTINGS
@given(
    seed=st.integers(0, 2**32 - 1),
    kind=KINDS,
    epsilons=st.lists(st.floats(0.01, 0.99), min_size=2, max_size=5),
)
def test_sets_grow_as_epsilon_decreases(seed, kind, epsilons):
    from service.conformal import conformal_threshold

    rng = np.random.default_rng(seed)
    heatmaps, centers = gaussian_blobs(rng, 40, size=32, noise=0.02)
    labels = centers + rng.normal(0, 2, centers.shape)
    calibration = nonconformity_scores(kind, heatmaps[:30], labels[:30])
    probes = rng.uniform(0, 32, (10, 2))
    previous_inside = np.zeros(10, dtype=bool)
    for epsilon in sorted(epsilons, reverse=True):
        threshold = conformal_threshold(calibration, epsilon)
        set_centers, shapes = prediction_sets(kind, heatmaps[30:], threshold)
        inside = contains(probes, set_centers, shapes)
        assert np.all(inside >= previous_inside)
        previous_inside = inside
