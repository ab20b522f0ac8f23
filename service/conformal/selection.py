"""Exact, vectorized top-K selection over the rows of a 2-D array.

``np.argpartition`` costs about a Python loop per row, so ``top_k_indices`` keeps each row's entries
above a cutoff guessed from a strided sample, sorts only those, and checks the cutoff kept the top K
(ties at the K-th value are among them, settled by column); rows where the guess fails take the exact
path. Any real dtype.
"""

from __future__ import annotations

import numpy as np

_SAMPLE_SIZE = 256  # values per row used to guess a candidate window
_MIN_FAST_ROW = 1024  # below this, the plain numpy path is already fast
_MAX_CANDIDATES = 512  # candidates sorted per row (SIMD sort range); more -> exact path


def top_k_indices(values: np.ndarray, k: int) -> np.ndarray:
    """Column indices (N, k), unordered, of the k largest entries of each row; ties at the k-th
    value go to the lowest column, so the selection is a function of the row."""
    n_rows, width = values.shape
    if not 1 <= k <= width:
        raise ValueError(f"k must be in [1, {width}], got {k}")
    if width < _MIN_FAST_ROW or 4 * k > width:
        return _exact_top_k(values, k)
    stride = width // _SAMPLE_SIZE
    sample = np.sort(values[:, ::stride], axis=1)
    rank_from_top = min(sample.shape[1], -(-2 * k // stride) + 1)
    candidates = values >= sample[:, -rank_from_top, None]
    counts = _row_counts(candidates)
    usable = (counts >= k) & (counts <= _MAX_CANDIDATES)
    if not usable.all():
        candidates[~usable] = False
        counts[~usable] = 0
    packed, columns = _pack_rows(candidates, values, -np.inf, counts, min_width=k + 1)
    # every entry tied with the row's k-th value is a candidate, in column order: ties are settled here
    chosen = _first_k(packed, -np.sort(-packed, axis=1)[:, k - 1, None], k)
    result = np.empty((n_rows, k), dtype=np.intp)
    result[usable] = columns[chosen & usable[:, None]].reshape(-1, k)
    slow_rows = np.flatnonzero(~usable)
    if slow_rows.size:
        result[slow_rows] = _exact_top_k(values[slow_rows], k)
    return result


def _row_counts(mask: np.ndarray) -> np.ndarray:
    """Number of True entries per row of a 2-D boolean array (a byte sum, ~5x count_nonzero)."""
    return mask.view(np.uint8).sum(axis=1, dtype=np.intp)


def _pack_rows(
    mask: np.ndarray, values: np.ndarray, fill: float, counts: np.ndarray, min_width: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Left-align the masked entries of each row (``counts`` of them) into (N, width) arrays
    padded with fill: their values and columns, in increasing column order."""
    flat_positions = np.flatnonzero(mask)
    rows, columns = np.divmod(flat_positions, mask.shape[1])
    starts = np.cumsum(counts) - counts
    slots = np.arange(rows.size) - starts[rows]
    width = max(int(counts.max(initial=0)), min_width)
    packed = np.full((mask.shape[0], width), fill, dtype=values.dtype)
    packed_columns = np.zeros((mask.shape[0], width), dtype=np.intp)
    packed[rows, slots] = values.ravel()[flat_positions]
    packed_columns[rows, slots] = columns
    return packed, packed_columns


def _exact_top_k(values: np.ndarray, k: int) -> np.ndarray:
    """Top-k by one partition per row; ties at the k-th value go to the lowest columns."""
    kth_value = -np.partition(-values, k - 1, axis=1)[:, k - 1, None]
    return np.nonzero(_first_k(values, kth_value, k))[1].reshape(values.shape[0], k)


def _first_k(values: np.ndarray, kth_value: np.ndarray, k: int) -> np.ndarray:
    """The k entries of each row kept: those above its k-th value, then those tied with it from the
    lowest column on."""
    greater = values > kth_value
    tied = values == kth_value
    missing = k - np.count_nonzero(greater, axis=1, keepdims=True)
    return greater | (tied & (np.cumsum(tied, axis=1) <= missing))
