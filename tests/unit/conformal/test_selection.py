"""``top_k_indices`` is the exact top K (ties to the lowest column) on every kind of row, shortcuts or not."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from service.conformal.selection import top_k_indices
from tests.unit.conformal.rows import row_cases


def definition(values: np.ndarray, k: int) -> np.ndarray:
    """The k largest of each row by a stable sort (lowest column first among equals), ascending."""
    return np.sort(np.argsort(-values, axis=1, kind="stable")[:, :k], axis=1)


def selected(values: np.ndarray, k: int) -> np.ndarray:
    return np.sort(top_k_indices(values, k), axis=1)


ROW_CASES = row_cases(np.random.default_rng(7))


@pytest.mark.parametrize("k", [1, 36, 100, 512])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("case", ROW_CASES)
def test_top_k_is_the_stable_sort_on_every_kind_of_row(case, dtype, k):
    with np.errstate(under="ignore", over="ignore"):
        values = ROW_CASES[case].astype(dtype)
    k = min(k, values.shape[1])
    np.testing.assert_array_equal(selected(values, k), definition(values, k))


DTYPES = st.sampled_from([np.float32, np.float64])


@st.composite
def arbitrary_rows(draw):
    dtype = np.dtype(draw(DTYPES))
    shape = draw(st.tuples(st.integers(1, 4), st.integers(1, 300)))
    return draw(hnp.arrays(dtype, shape, elements=st.floats(-1e6, 1e6, width=dtype.itemsize * 8)))


@st.composite
def rows_of_few_levels(draw):
    """Ties everywhere: every value is one of at most five levels; wide enough for the sampled shortcut."""
    shape = draw(st.tuples(st.integers(1, 3), st.sampled_from([2, 400, 1024, 4096])))
    levels = draw(st.lists(st.floats(-10, 10, width=32), min_size=1, max_size=5))
    choice = draw(hnp.arrays(np.int64, shape, elements=st.integers(0, len(levels) - 1)))
    return np.asarray(levels, dtype=draw(DTYPES))[choice]


@settings(max_examples=300, deadline=None)
@given(values=st.one_of(arbitrary_rows(), rows_of_few_levels()), data=st.data())
def test_top_k_is_the_stable_sort_on_generated_rows(values, data):
    k = data.draw(st.integers(1, values.shape[1]))
    np.testing.assert_array_equal(selected(values, k), definition(values, k))


def test_k_outside_the_row_is_refused():
    with pytest.raises(ValueError, match=r"k must be in \[1, 8\]"):
        top_k_indices(np.ones((2, 8)), 9)
