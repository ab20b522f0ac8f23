"""Anchor statistics read from the raw heatmap values, without a float64 copy of the batch.

The anchor weight of a raw value v is w = fl(v - min) in float64: a monotone
non-decreasing map of v. Order statistics commute with such a map, so the
argmax and the top-K pixels can be selected on the raw values (float32 from the
detector: half the memory traffic of float64), and only the few selected values
are converted. A monotone map can change a selection in one way only, by
rounding two distinct raw values onto one weight; ``isolated`` checks that no
other raw value shares the weight of a value that decides a selection (the
argmax, the K-th value), and the statistics module recomputes every row where
a check fails on the exact float64 path. The answer never depends on the
shortcut.

The normalizer S of ``peak`` (the sum of the weights at or above the median)
needs the exact median of every map: ``peak`` rows take the exact float64 path.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .selection import top_k_indices


@dataclass(frozen=True)
class RawExtremes:
    """Per row: first index of the largest raw value, and the min and max as float64."""

    argmax: np.ndarray
    minimum: np.ndarray
    maximum: np.ndarray


def raw_extremes(flat: np.ndarray) -> RawExtremes:
    argmax = flat.argmax(axis=1)
    maximum = flat[np.arange(flat.shape[0]), argmax]
    return RawExtremes(argmax, flat.min(axis=1).astype(np.float64), maximum.astype(np.float64))


def anchor_weights(values: np.ndarray, minimum: np.ndarray) -> np.ndarray:
    """fl(v - min) in float64, the anchor weight of raw values (N,) or (N, M)."""
    minimum = minimum if values.ndim == 1 else minimum[:, None]
    return values.astype(np.float64) - minimum


def isolated(values: np.ndarray, minimum: np.ndarray) -> np.ndarray:
    """(N,) True where no other raw value of the row can share the weight of ``values``.

    Raw values are discrete: every other value lies at or beyond the neighbouring
    representable values of the raw dtype, so it suffices that those map to
    strictly smaller and larger weights.
    """
    weight = anchor_weights(values, minimum)
    below = anchor_weights(np.nextafter(values, -np.inf), minimum)
    above = anchor_weights(np.nextafter(values, np.inf), minimum)
    return (below < weight) & (weight < above)


def raw_top_k(flat: np.ndarray, k: int, minimum: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Top-k column indices (N, k) and their weights, selected on the raw values.

    Equal to the top-k of the weights (ties towards the lowest column) where the
    returned (N,) flag is True. The caller guarantees 2k <= H*W, so the
    below-median zeroing never reaches the top k.
    """
    indices = top_k_indices(flat, k)
    values = np.take_along_axis(flat, indices, axis=1)
    exact = isolated(values.min(axis=1), minimum)
    return indices, anchor_weights(values, minimum), exact
