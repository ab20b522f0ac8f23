"""The native anchor-median kernel equals numpy's median-masked sum on every kind of row."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from service.conformal.kernel import native_kernel_available, upper_half_sums


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
        "service/conformal/_upper_half*.so is missing: install a C compiler (apt install gcc) "
        "and rerun pip install -e ."
    )


def _row_cases(rng: np.random.Generator) -> dict[str, np.ndarray]:
    noise = rng.normal(size=(30, 4096))
    return {
        "gaussian noise": noise,
        "few distinct values (ties at the median)": np.round(noise * 2),
        "mostly exact zeros": np.where(rng.random((30, 4096)) < 0.7, 0.0, rng.random((30, 4096))),
        "odd width": noise[:, :4095],
        "width 2": noise[:, :2],
        "width 3": noise[:, :3],
        "constant": np.full((4, 100), 3.5),
        "huge magnitudes": noise * 1e30,
        "subnormal magnitudes": noise * 1e-40,
        "two scales (weights merge)": np.hstack([noise[:, :2048] * 1e-30, noise[:, 2048:] * 1e20]),
        "heavy tail": rng.exponential(size=(30, 4096)) ** 8,
        "half the row at the maximum": np.where(noise > 0, noise.max(), noise),
        "negative values only": -np.abs(noise) - 5.0,
    }


ROW_CASES = _row_cases(np.random.default_rng(7))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("case", ROW_CASES)
def test_kernel_equals_the_median_masked_sum(case, dtype):
    with np.errstate(under="ignore", over="ignore"):
        flat = ROW_CASES[case].astype(dtype)
    np.testing.assert_allclose(kernel_sums(flat), median_masked_sum(flat), rtol=1e-12, atol=0)


def test_rows_too_narrow_or_of_another_dtype_are_left_to_numpy():
    assert upper_half_sums(np.ones((2, 1), np.float32), np.ones(2), np.ones(2)) is None
    assert upper_half_sums(np.ones((2, 8), np.float16), np.ones(2), np.ones(2)) is None
    assert upper_half_sums(np.ones((2, 8), ">f8"), np.ones(2), np.ones(2)) is None
    assert upper_half_sums(np.ones(8, np.float32), np.ones(1), np.ones(1)) is None


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
