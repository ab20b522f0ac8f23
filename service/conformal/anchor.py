"""Anchor statistics read from the raw heatmap values, without a float64 copy of the batch.

The anchor weight of a raw value v is w = fl(v - min) in float64: a monotone
non-decreasing map of v. Order statistics commute with such a map, so the
argmax, the top-K pixels and the two middle values behind the median can be
selected on the raw values (float32 from the detector: half the memory traffic
of float64), and only the few selected values are converted. A monotone map can
change a selection in one way only, by rounding two distinct raw values onto
one weight; ``isolated`` checks that no other raw value shares the weight of a
value that decides a selection (the argmax, the K-th value, the lower middle
value), and the statistics module recomputes every row where a check or a
sampling guess fails on the exact float64 path. The answer never depends on
the shortcut.

The normalizer S of ``peak`` (the sum of the weights at or above the median)
needs the exact median, and a per-row ``np.partition`` (~25-45 us per 4096
values) would cost more than the whole per-heatmap reference loop. Instead a
sorted strided sample brackets the two middle ranks, one pass per bound counts
and marks the values inside the bracket, and only those (a few hundred per
row) are sorted. S itself is one float64 row sum of max(v, low), accepted only
where a rigorous rounding-error bound is below 1e-11 relative.

Measured (python -m benchmarks.bench_conformal, 76 float32 maps 64x64, machine
shared with a training job, load average ~11 on 2 cores; before -> after, same
run conditions): var 93-114 -> 18-19 us/map (~40x the per-map loop), cov
109-114 -> 14-19 us/map (~40x), peak 131-139 -> 32 us/map (3-4x; loop 100-150).
Peak stays far from 20x in pure numpy: an exact median needs every value
compared and the bracket values extracted, and with about half of a row near
the median the masks are random, so ``np.flatnonzero`` / boolean indexing run
at branch-misprediction speed (~0.4-1.2 ns per value, ~400 us per batch under
this load) and the sample misses the bracket on a few percent of rows, which
then pay the exact path (np.median, ~45 us each). The per-map loop's own cost is
one np.partition plus ~15 small numpy calls, ~95-150 us, so 20x leaves under
~5-7 us per map for about eight full passes over the batch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .selection import pack_rows, row_counts, top_k_indices

_MEDIAN_SAMPLE = 512  # strided sample that brackets the median (np.sort is fast up to 512)
_MEDIAN_MARGIN = 24  # sample ranks either side of the sample median (~2 standard deviations)
_MAX_BRACKET = 512  # bracket values sorted per row; wider rows take the exact path
_SUM_TOLERANCE = 1e-11  # accepted relative rounding-error bound of S


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


def upper_half_weight_sums(flat: np.ndarray, minimum: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """S = sum of the anchor weights at or above their median (np.median's), float64.

    Returns S (N,) and a flag (N,), False where the bracket missed, the middle
    value is not isolated or the rounding bound fails; those rows need the exact path.
    """
    n_rows, width = flat.shape
    lower_mid, upper_mid = (width - 1) // 2, width // 2
    sample = np.sort(flat[:, :: max(width // _MEDIAN_SAMPLE, 1)], axis=1)
    centre = sample.shape[1] // 2
    low = sample[:, max(centre - _MEDIAN_MARGIN, 0), None]
    high = sample[:, min(centre + _MEDIAN_MARGIN, sample.shape[1] - 1), None]
    at_least_low = flat >= low
    bracket = at_least_low & (flat <= high)
    n_below = width - row_counts(at_least_low)
    n_bracket = row_counts(bracket)
    tied = low[:, 0] == high[:, 0]  # e.g. a zero background: both middle values are ``low``
    ok = (n_below <= lower_mid) & (n_below + n_bracket > upper_mid) & ((n_bracket <= _MAX_BRACKET) | tied)
    unpacked = ~ok | tied
    if unpacked.any():
        bracket[unpacked] = False
        n_bracket[unpacked] = 0
    inside = np.sort(pack_rows(bracket, flat, np.inf, n_bracket)[0], axis=1)
    rows = np.arange(n_rows)
    first = np.clip(lower_mid - n_below, 0, inside.shape[1] - 1 - (upper_mid - lower_mid))
    middle_low = np.where(tied, low[:, 0], inside[rows, first])
    middle_high = np.where(tied, low[:, 0], inside[rows, first + upper_mid - lower_mid])
    below_weight = anchor_weights(middle_low, minimum)
    median = (below_weight + anchor_weights(middle_high, minimum)) / 2 if width % 2 == 0 else below_weight
    take_low = below_weight >= median  # the lower middle value itself is not zeroed
    ok &= ~take_low | isolated(middle_low, minimum)
    threshold = np.where(take_low, middle_low, middle_high)[:, None]
    dropped = np.where(inside < threshold, inside, 0).astype(np.float64).sum(axis=1)
    total = np.maximum(flat, low).astype(np.float64) @ np.ones(width)
    count = width - n_below - np.count_nonzero(inside < threshold, axis=1)
    low = low[:, 0].astype(np.float64)
    sums = (total - n_below * low - dropped) - count * minimum
    scale = np.abs(total) + 3 * width * np.abs(low) + np.abs(dropped) + width * np.abs(minimum)
    ok &= 2 * width * np.finfo(np.float64).eps * scale <= _SUM_TOLERANCE * sums
    return sums, ok
