"""Anchor statistics selected on the raw heatmap values, without a float64 copy of the batch.

The anchor weight w = fl(v - min) in float64 is monotone non-decreasing in the raw value v, so the
argmax and the top-K pixels can be selected on the raw values (float32: half the memory traffic)
and only the selected ones converted. A monotone map changes a selection only by rounding two
distinct raw values onto one weight: ``isolated`` checks that no other raw value shares the weight
of a deciding value, and rows failing it are recomputed on the exact float64 path.
"""

from __future__ import annotations

import numpy as np

from .selection import top_k_indices


def anchor_weights(values: np.ndarray, minimum: np.ndarray) -> np.ndarray:
    """fl(v - min) in float64, the anchor weight of raw values (N,) or (N, M)."""
    return values.astype(np.float64) - (minimum if values.ndim == 1 else minimum[:, None])


def isolated(values: np.ndarray, minimum: np.ndarray) -> np.ndarray:
    """(N,) True where no other raw value of the row can share the weight of ``values``: the
    neighbouring representable raw values map to strictly smaller and larger weights."""
    weight = anchor_weights(values, minimum)
    below = anchor_weights(np.nextafter(values, -np.inf), minimum)
    above = anchor_weights(np.nextafter(values, np.inf), minimum)
    return (below < weight) & (weight < above)


def raw_top_k(flat: np.ndarray, k: int, minimum: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Top-k column indices (N, k) and their weights, selected on the raw values; equal to the
    top-k of the weights (ties towards the lowest column) where the returned (N,) flag is True.
    The caller guarantees 2k <= H*W, so the below-median zeroing never reaches the top k."""
    indices = top_k_indices(flat, k)
    values = np.take_along_axis(flat, indices, axis=1)
    return indices, anchor_weights(values, minimum), isolated(values.min(axis=1), minimum)
