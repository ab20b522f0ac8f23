"""Exact, vectorized top-K selection over the rows of a 2-D array.

``np.argpartition`` on a whole (N, P) batch costs about as much per row as a
Python loop (introselect is bound by branch mispredictions), so ``top_k_indices``
first shrinks each row to the entries above a cutoff guessed from a strided
sample, partitions only those, and verifies that the cutoff kept every entry
that could belong to the top K. Rows where the guess fails or the K-th value is
tied take the exact slow path, so the answer never depends on the shortcut.
"""

from __future__ import annotations

import numpy as np

_SAMPLE_SIZE = 256  # values per row used to guess a candidate window
_MIN_FAST_ROW = 1024  # below this, the plain numpy path is already fast


def top_k_indices(values: np.ndarray, k: int) -> np.ndarray:
    """Column indices (N, k), unordered, of the k largest entries of each row.

    Ties at the k-th value are broken towards the lowest column index, so the
    selection is a well-defined function of the row (row-major order for a
    flattened heatmap).
    """
    n_rows, width = values.shape
    if not 1 <= k <= width:
        raise ValueError(f"k must be in [1, {width}], got {k}")
    if width < _MIN_FAST_ROW or 4 * k > width:
        return _exact_top_k(values, k)
    stride = width // _SAMPLE_SIZE
    sample = np.sort(values[:, ::stride], axis=1)
    rank_from_top = min(sample.shape[1], -(-2 * k // stride) + 1)
    cutoff = sample[:, -rank_from_top, None]
    candidates = values >= cutoff
    n_candidates = np.count_nonzero(candidates, axis=1)
    usable = (n_candidates >= k) & (n_candidates <= 8 * k)
    result = np.empty((n_rows, k), dtype=np.intp)
    fast_rows = np.flatnonzero(usable)
    if fast_rows.size:
        packed, columns = _pack_rows(candidates[fast_rows], values[fast_rows], fill=-np.inf)
        chosen = np.argpartition(-packed, k - 1, axis=1)[:, :k]
        chosen_values = np.take_along_axis(packed, chosen, axis=1)
        kth_value = chosen_values.min(axis=1, keepdims=True)
        unambiguous = np.count_nonzero(packed >= kth_value, axis=1) == k
        result[fast_rows] = np.take_along_axis(columns, chosen, axis=1)
        usable[fast_rows[~unambiguous]] = False
    slow_rows = np.flatnonzero(~usable)
    if slow_rows.size:
        result[slow_rows] = _exact_top_k(values[slow_rows], k)
    return result


def _exact_top_k(values: np.ndarray, k: int) -> np.ndarray:
    """Top-k by one partition per row; ties at the k-th value go to the lowest columns."""
    kth_value = -np.partition(-values, k - 1, axis=1)[:, k - 1, None]
    greater = values > kth_value
    tied = values == kth_value
    missing = k - np.count_nonzero(greater, axis=1, keepdims=True)
    selected = greater | (tied & (np.cumsum(tied, axis=1) <= missing))
    return np.nonzero(selected)[1].reshape(values.shape[0], k)


def _pack_rows(mask: np.ndarray, values: np.ndarray, fill: float) -> tuple[np.ndarray, np.ndarray]:
    """Left-align the masked entries of each row into a (N, max count) array padded with fill."""
    counts = np.count_nonzero(mask, axis=1)
    rows, columns = np.divmod(np.flatnonzero(mask), mask.shape[1])
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    positions = np.arange(rows.size) - starts[rows]
    width = max(int(counts.max()), 1)
    packed = np.full((mask.shape[0], width), fill)
    packed_columns = np.zeros((mask.shape[0], width), dtype=np.intp)
    packed[rows, positions] = values[rows, columns]
    packed_columns[rows, positions] = columns
    return packed, packed_columns
