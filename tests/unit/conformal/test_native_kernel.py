"""The native anchor kernel equals its numpy definitions on every kind of row.

The median-masked sum (``peak``'s normalizer) to 1e-12; the extremes, the first
maximum and the top-K selection exactly; the top-K spread, and so the statistics
behind ``var`` and ``cov``, bit for bit, against the numpy path that serves when the
kernel is not built.
"""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from service.conformal import heatmap_statistics, kernel, nonconformity_scores
from service.conformal.kernel import anchor_peaks, native_kernel_available, top_k_spread, upper_half_sums
from service.conformal.selection import top_k_indices
from service.conformal.statistics import _spread
from tests.unit.conformal.rows import row_cases


def median_masked_sum(flat: np.ndarray) -> np.ndarray:
    """The definition: anchor weights, np.median, sum of the weights at or above it."""
    weights = flat.astype(np.float64) - flat.min(axis=1, keepdims=True).astype(np.float64)
    median = np.median(weights, axis=1, keepdims=True)
    return np.where(weights >= median, weights, 0.0).sum(axis=1)


def kernel_sums(flat: np.ndarray) -> np.ndarray:
    sums = upper_half_sums(flat, flat.min(axis=1).astype(np.float64), flat.max(axis=1).astype(np.float64))
    assert sums is not None
    return sums


def test_the_native_kernel_is_built():
    assert native_kernel_available(), (
        "service/conformal/_upper_half*.so is missing or was built from older sources: install a "
        "C compiler (apt install gcc) and rerun pip install -e ."
    )


def test_a_build_of_other_sources_is_not_loaded(monkeypatch):
    monkeypatch.setattr(kernel, "_VERSION", kernel._VERSION + 1)
    kernel._library.cache_clear()
    try:
        assert not native_kernel_available()
        assert anchor_peaks(np.ones((2, 8))) is None and top_k_spread(np.ones((2, 8)), 2, 4) is None
    finally:
        monkeypatch.undo()
        kernel._library.cache_clear()
    assert native_kernel_available()


# finite rows: non-finite ones are uninformative on both paths (test_raw_anchor.py)
ROW_CASES = {name: rows for name, rows in row_cases(np.random.default_rng(7)).items() if name != "infinities"}


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("case", ROW_CASES)
def test_kernel_equals_the_median_masked_sum(case, dtype):
    with np.errstate(under="ignore", over="ignore"):
        flat = ROW_CASES[case].astype(dtype)
    np.testing.assert_allclose(kernel_sums(flat), median_masked_sum(flat), rtol=1e-12, atol=0)


@pytest.mark.parametrize("k", [1, 36, 100, 512])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("case", ROW_CASES)
def test_top_k_equals_numpy_selection_on_every_kind_of_row(case, dtype, k):
    with np.errstate(under="ignore", over="ignore"):
        flat = ROW_CASES[case].astype(dtype)
    k = min(k, flat.shape[1])
    np.testing.assert_array_equal(top_k_spread(flat, k, 64).indices, top_k_indices(weights_of(flat), k))


def test_rows_too_narrow_or_of_another_dtype_are_left_to_numpy():
    assert upper_half_sums(np.ones((2, 1), np.float32), np.ones(2), np.ones(2)) is None
    assert upper_half_sums(np.ones((2, 8), np.float16), np.ones(2), np.ones(2)) is None
    assert upper_half_sums(np.ones((2, 8), ">f8"), np.ones(2), np.ones(2)) is None
    assert upper_half_sums(np.ones(8, np.float32), np.ones(1), np.ones(1)) is None
    assert anchor_peaks(np.ones((2, 8), np.float16)) is None
    assert top_k_spread(np.ones((2, 8), ">f8"), 2, 4) is None


def test_extremes_must_have_one_value_per_row():
    with pytest.raises(ValueError, match="one value per row"):
        upper_half_sums(np.ones((8, 16), np.float32), np.zeros(1), np.ones(1))


def test_unaligned_and_strided_rows_give_the_same_sums():
    rows = ROW_CASES["gaussian noise"][:4].astype(np.float32)
    buffer = np.zeros(rows.nbytes + 1, np.uint8)
    unaligned = np.frombuffer(buffer.data, np.float32, rows.size, offset=1).reshape(rows.shape)
    unaligned[...] = rows
    strided = np.repeat(rows, 2, axis=1)[:, ::2]
    for flat in (unaligned, strided):
        np.testing.assert_array_equal(kernel_sums(flat), kernel_sums(rows))
        np.testing.assert_array_equal(top_k_spread(flat, 50, 64).spread, top_k_spread(rows, 50, 64).spread)


DTYPES = st.sampled_from([np.float32, np.float64])


@st.composite
def arbitrary_rows(draw):
    dtype = np.dtype(draw(DTYPES))
    shape = draw(st.tuples(st.integers(1, 4), st.integers(2, 300)))
    return draw(hnp.arrays(dtype, shape, elements=st.floats(-1e6, 1e6, width=dtype.itemsize * 8)))


@st.composite
def rows_of_few_levels(draw):
    """Ties everywhere: every value is one of at most five levels."""
    shape = draw(st.tuples(st.integers(1, 3), st.integers(2, 400)))
    levels = draw(st.lists(st.floats(-10, 10, width=32), min_size=1, max_size=5))
    choice = draw(hnp.arrays(np.int64, shape, elements=st.integers(0, len(levels) - 1)))
    return np.asarray(levels, dtype=draw(DTYPES))[choice]


@settings(max_examples=600, deadline=None)
@given(values=st.one_of(arbitrary_rows(), rows_of_few_levels()))
def test_kernel_equals_the_median_masked_sum_on_generated_rows(values):
    np.testing.assert_allclose(kernel_sums(values), median_masked_sum(values), rtol=1e-12, atol=1e-300)


def weights_of(flat: np.ndarray) -> np.ndarray:
    """The anchor weights without the median zeroing: float64(v) - min, per row."""
    return flat.astype(np.float64) - flat.min(axis=1, keepdims=True).astype(np.float64)


def assert_same_bits(actual: np.ndarray, expected: np.ndarray) -> None:
    assert actual.dtype == expected.dtype and actual.shape == expected.shape
    assert actual.tobytes() == expected.tobytes(), f"{actual!r} != {expected!r}"


@st.composite
def structured_rows(draw):
    """Rows of heatmap-like and adversarial kinds, wide enough for the sampled search (width >= 2048)."""
    dtype = draw(DTYPES)
    n, width = draw(st.integers(1, 3)), draw(st.sampled_from([1, 2, 3, 64, 1000, 2048, 4095, 4096, 5000]))
    kinds = ["noise", "blob", "levels", "zeros", "constant", "scales", "maximum", "tail"]
    kind = draw(st.sampled_from(kinds))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    noise = rng.normal(size=(n, width))
    columns, rows = np.arange(width) % 64, np.arange(width) // 64
    center = rng.uniform(0, 64, (n, 2, 1))
    blob = np.exp(-((columns - center[:, 0]) ** 2 + (rows - center[:, 1]) ** 2) / rng.uniform(2, 50, (n, 1)))
    values = {
        "noise": noise,
        "blob": blob + rng.uniform(0, 0.1) * noise,
        "levels": np.round(noise * rng.uniform(0.5, 3)),
        "zeros": np.where(rng.random((n, width)) < rng.uniform(0.5, 0.999), 0.0, np.abs(noise)),
        "constant": np.full((n, width), rng.normal()),
        "scales": np.where(rng.random((n, width)) < 0.5, noise * 1e-30, noise * 1e20),
        "maximum": np.where(noise > 0, 1.0, noise),
        "tail": rng.exponential(size=(n, width)) ** 8,
    }[kind]
    k = draw(st.one_of(st.just(1), st.just(width), st.integers(1, max(1, width // 8)), st.integers(1, width)))
    with np.errstate(over="ignore", under="ignore"):
        return values.astype(dtype), k


SELECTION = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@SELECTION
@given(case=structured_rows())
def test_native_top_k_equals_numpy_selection_and_spread(case):
    flat, k = case
    result = top_k_spread(flat, k, 64)
    weights = weights_of(flat)
    expected = top_k_indices(weights, k)  # ascending, ties towards the lowest column
    np.testing.assert_array_equal(result.indices, expected)
    with np.errstate(invalid="ignore", divide="ignore"):  # constant rows: 0 / 0
        spread = _spread(expected, np.take_along_axis(weights, expected, axis=1), 64)
    fields = np.stack(
        [
            *spread["mean"].T,
            spread["covariance"][:, 0, 0],
            spread["covariance"][:, 0, 1],
            spread["covariance"][:, 1, 1],
        ],
        axis=1,
    )
    assert_same_bits(result.spread, fields)


@settings(max_examples=300, deadline=None)
@given(values=st.one_of(arbitrary_rows(), rows_of_few_levels()), data=st.data())
def test_native_top_k_equals_numpy_selection_on_generated_rows(values, data):
    k = data.draw(st.integers(1, values.shape[1]))
    expected = top_k_indices(weights_of(values), k)
    np.testing.assert_array_equal(top_k_spread(values, k, 7).indices, expected)


@SELECTION
@given(case=structured_rows())
def test_native_extremes_and_first_maximum_equal_numpy(case):
    flat, _ = case
    if flat.shape[1] < 2:
        assert anchor_peaks(flat) is None
        return
    peaks = anchor_peaks(flat)
    np.testing.assert_array_equal(peaks.minimum, flat.min(axis=1).astype(np.float64))
    np.testing.assert_array_equal(peaks.maximum, flat.max(axis=1).astype(np.float64))
    np.testing.assert_array_equal(peaks.argmax, weights_of(flat).argmax(axis=1))
    np.testing.assert_allclose(peaks.sums, median_masked_sum(flat), rtol=1e-12, atol=1e-300)


def test_the_first_maximum_is_the_weights_not_the_raw_values():
    row = np.full((1, 4096), -1e6)
    row[0, 100], row[0, 3000] = 1.0, 1.0 + 2**-40  # one weight apart from -1e6, distinct raw values
    assert row.argmax() == 3000
    assert weights_of(row)[0, 100] == weights_of(row)[0, 3000]
    assert anchor_peaks(row).argmax[0] == 100


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_rows_that_are_not_finite_get_nan_or_infinite_extremes_and_no_selection(dtype):
    rows = np.tile(np.linspace(0, 1, 4096, dtype=dtype), (4, 1))
    rows[0, 7], rows[1, 9], rows[2, 11] = np.nan, np.inf, -np.inf
    for result in (anchor_peaks(rows), top_k_spread(rows, 100, 64)):
        np.testing.assert_array_equal(result.minimum, [np.nan, 0, -np.inf, 0])
        np.testing.assert_array_equal(result.maximum, [np.nan, np.inf, 1, 1])
    spread = top_k_spread(rows, 100, 64)
    assert not spread.indices[:3].any() and not spread.spread[:3].any()
    np.testing.assert_array_equal(spread.indices[3], np.arange(3996, 4096))


def test_k_outside_the_row_is_refused():
    with pytest.raises(ValueError, match="1 <= k <= 8"):
        top_k_spread(np.ones((2, 8)), 9, 4)
    with pytest.raises(ValueError, match="grid_width"):
        top_k_spread(np.ones((2, 8)), 2, 0)


@st.composite
def adversarial_heatmaps(draw):
    """Batches (N, H, W), float32 or float64 without NaN, and a top K, k = 1 and k = H*W included."""
    dtype = draw(DTYPES)
    height, width = draw(st.sampled_from([(1, 1), (1, 2), (3, 5), (24, 24), (32, 32), (64, 64), (48, 80)]))
    kind = draw(st.sampled_from(["noise", "blob", "levels", "zeros", "constant", "generated"]))
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
            "generated": noise,
        }[kind].astype(dtype)
    size = height * width
    k = draw(st.one_of(st.just(1), st.just(size), st.integers(1, max(1, size // 2)), st.integers(1, size)))
    return heatmaps, k


def statistics_and_scores(heatmaps: np.ndarray, k: int) -> tuple:
    keypoints = np.full((len(heatmaps), 2), 3.25)
    scores = {kind: nonconformity_scores(kind, heatmaps, keypoints, top_k=k) for kind in ("var", "cov")}
    return heatmap_statistics(heatmaps, top_k=k), scores


@settings(
    max_examples=250,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
@given(case=adversarial_heatmaps())
def test_statistics_are_bit_for_bit_those_of_the_numpy_path(case, monkeypatch):
    heatmaps, k = case
    native, native_scores = statistics_and_scores(heatmaps, k)
    with monkeypatch.context() as patch:
        patch.setattr(kernel, "_library", lambda: None)  # as if the kernel were not built
        numpy, numpy_scores = statistics_and_scores(heatmaps, k)
    for name in ("uninformative", "mean", "covariance", "peak_location"):
        assert_same_bits(getattr(native, name), getattr(numpy, name))
    for kind in ("var", "cov"):
        assert_same_bits(native_scores[kind], numpy_scores[kind])
    # peak's normalizer is summed in another order by the kernel (a few ulp)
    np.testing.assert_allclose(native.peak_probability, numpy.peak_probability, rtol=1e-12, atol=0)
