"""Anchor statistics read from the raw heatmap values, without a float64 copy of the batch.

The anchor weight w = fl(v - min) is monotone in v, so the top-K pixels can be selected on the raw
(float32) values and only the selected ones converted. Rounding may map two raw values onto one
weight: ``isolated`` checks that no other value shares the weight of one that decides a selection,
and rows failing it take the exact float64 path (as do ``peak`` rows: their normalizer needs the
exact median). The answer never depends on the shortcut.
"""

from __future__ import annotations

import numpy as np

from .selection import top_k_indices


def anchor_weights(values: np.ndarray, minimum: np.ndarray) -> np.ndarray:
    """fl(v - min) in float64, the anchor weight of raw values (N,) or (N, M)."""
    minimum = minimum if values.ndim == 1 else minimum[:, None]
    return values.astype(np.float64) - minimum


def isolated(values: np.ndarray, minimum: np.ndarray) -> np.ndarray:
    """(N,) True where no other raw value of the row can share the weight of ``values``: enough
    that the neighbouring representable raw values map to strictly smaller and larger weights."""
    weight = anchor_weights(values, minimum)
    below = anchor_weights(np.nextafter(values, -np.inf), minimum)
    above = anchor_weights(np.nextafter(values, np.inf), minimum)
    return (below < weight) & (weight < above)


def raw_top_k(flat: np.ndarray, k: int, minimum: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Top-k column indices (N, k) and their weights, selected on the raw values: the weights' top-k
    where the returned (N,) flag is True (the caller guarantees 2k <= H*W)."""
    indices = top_k_indices(flat, k)
    values = np.take_along_axis(flat, indices, axis=1)
    exact = isolated(values.min(axis=1), minimum)
    return indices, anchor_weights(values, minimum), exact
