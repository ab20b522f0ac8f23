"""The native anchor kernel (``native/upper_half.c``), loaded with ctypes.

Per heatmap, ``peak`` needs S = the sum of the anchor weights at or above their
median (an exact median of 4096 values) and the first index of the largest
weight; ``var`` and ``cov`` need the K largest weights and their weighted
spread. numpy's exact tools, ``np.partition`` and ``np.argpartition``, cost
about as much per map as a whole per-heatmap loop. The kernel selects by
vectorized counting passes instead (``python -m benchmarks.bench_conformal``
prints the figures), and reads each map's extremes in the same call.

It is built by ``pip install`` when a C compiler is present (an optional
extension: no compiler, no failure). Without it every function here returns
None and callers take the numpy path: the same selections and, for the spread,
the same bits (``statistics._spread`` sums in the kernel's order).
"""

from __future__ import annotations

import ctypes
import functools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

_LIBRARY = "_upper_half"
_VERSION = 4  # cks_kernel_version() of the sources this module expects
_TYPES = {np.dtype(np.float32): "f32", np.dtype(np.float64): "f64"}
_POINTER, _SIZE = ctypes.c_void_p, ctypes.c_int64
# The entry points and their arguments: rows, N, M, then sizes and output arrays.
_ENTRY_POINTS = {
    "cks_anchor_peaks": (_POINTER, _SIZE, _SIZE, _POINTER, _POINTER, _POINTER, _POINTER),
    "cks_top_k_spread": (_POINTER, _SIZE, _SIZE, _SIZE, _SIZE, _POINTER, _POINTER, _POINTER, _POINTER),
}
_MAX_WIDTH = 2**31 - 1  # the kernel counts in 32-bit lanes
SPREAD_FIELDS = ("mean_x", "mean_y", "sxx", "sxy", "syy")  # the columns of TopKSpread.spread


@dataclass(frozen=True)
class AnchorPeaks:
    """``peak``'s anchor statistics of N rows.

    ``minimum`` and ``maximum`` are each row's min and max as float64 (NaN for both
    when the row holds a NaN, as numpy's); ``sums`` (S) and ``argmax`` (the first
    index of the largest weight) are set for rows whose extremes are finite, 0 elsewhere.
    """

    minimum: np.ndarray
    maximum: np.ndarray
    sums: np.ndarray
    argmax: np.ndarray


@dataclass(frozen=True)
class TopKSpread:
    """The top-K selection of N rows and its spread.

    ``minimum`` and ``maximum`` as in ``AnchorPeaks``; ``indices`` (N, k), the
    selected columns in ascending order, and ``spread`` (N, 5), columns
    ``SPREAD_FIELDS``, are set for rows whose extremes are finite, zeros elsewhere.
    """

    minimum: np.ndarray
    maximum: np.ndarray
    indices: np.ndarray
    spread: np.ndarray


@functools.cache
def _library() -> ctypes.CDLL | None:
    try:
        library = np.ctypeslib.load_library(_LIBRARY, Path(__file__).parent)
        current = library.cks_kernel_version() == _VERSION
        for name, arguments in _ENTRY_POINTS.items():
            for suffix in _TYPES.values():
                getattr(library, f"{name}_{suffix}").argtypes = arguments  # plain ints then pass as is
    except (OSError, AttributeError):  # not built, or a build of older sources
        return None
    return library if current else None


def native_kernel_available() -> bool:
    """True when the compiled kernel was built from the current sources and loads."""
    return _library() is not None


def anchor_peaks(flat: np.ndarray) -> AnchorPeaks | None:
    """``peak``'s anchor statistics of raw rows (N, M), M >= 2; None without the kernel.

    S is the sum of the weights w = float64(v) - min that are >= their median
    (np.median's), summed in another order than numpy's (a few ulp apart). The
    first maximum is the first index of the largest weight, which can precede
    ``flat.argmax(axis=1)`` when rounding gives the largest raw value and smaller
    ones one weight (float64 rows far from their minimum).
    """
    rows = _rows(flat, min_width=2)
    return None if rows is None else _anchor_peaks(rows)


def top_k_spread(flat: np.ndarray, k: int, grid_width: int) -> TopKSpread | None:
    """The k largest weights w = float64(v) - min of each raw row (N, M) and their spread.

    The columns, ascending, are ``selection.top_k_indices`` of the weights (ties at
    the k-th value towards the lowest index). The spread is that of their pixel
    centres (row-major, ``grid_width`` pixels a row) under the renormalized
    weights, as ``statistics._spread`` computes it: the same bits. None without
    the kernel.
    """
    rows = _rows(flat, min_width=1)
    if rows is None:
        return None
    if not 1 <= k <= rows.shape[1] or grid_width < 1:
        raise ValueError(f"need 1 <= k <= {rows.shape[1]} and grid_width >= 1, got k={k}, {grid_width}")
    n = rows.shape[0]
    minimum, maximum = np.empty(n), np.empty(n)
    indices = np.empty((n, k), dtype=np.int64)
    spread = np.empty((n, len(SPREAD_FIELDS)))
    _call("cks_top_k_spread", rows, k, grid_width, minimum, maximum, indices, spread)
    return TopKSpread(minimum, maximum, indices.astype(np.intp, copy=False), spread)


def upper_half_sums(flat: np.ndarray, minimum: np.ndarray, maximum: np.ndarray) -> np.ndarray | None:
    """S (N,) per row of finite raw values (N, M), M >= 2; None without the kernel.

    ``minimum`` and ``maximum`` are the rows' extremes as float64, checked for
    shape only (the kernel reads the extremes itself). See ``anchor_peaks``.
    """
    rows = _rows(flat, min_width=2)
    if rows is None:
        return None
    if np.shape(minimum) != (rows.shape[0],) or np.shape(maximum) != (rows.shape[0],):
        raise ValueError(f"minimum and maximum need one value per row, {rows.shape[0]} rows")
    return _anchor_peaks(rows).sums


def _anchor_peaks(rows: np.ndarray) -> AnchorPeaks:
    n = rows.shape[0]
    minimum, maximum, sums = np.empty(n), np.empty(n), np.empty(n)
    argmax = np.empty(n, dtype=np.int64)
    _call("cks_anchor_peaks", rows, minimum, maximum, sums, argmax)
    return AnchorPeaks(minimum, maximum, sums, argmax.astype(np.intp, copy=False))


def _rows(flat: np.ndarray, min_width: int) -> np.ndarray | None:
    """The rows as a C-ordered, aligned, native-order array; None where the kernel cannot take them."""
    supported = flat.ndim == 2 and flat.dtype in _TYPES and min_width <= flat.shape[1] <= _MAX_WIDTH
    if _library() is None or not supported:
        return None
    return np.require(flat, requirements="CA")


def _call(name: str, flat: np.ndarray, *arguments: object) -> None:
    function = _function(name, flat.dtype)
    addresses = [a.ctypes.data if isinstance(a, np.ndarray) else a for a in arguments]
    status = function(flat.ctypes.data, flat.shape[0], flat.shape[1], *addresses)
    if status != 0:
        raise RuntimeError(f"native anchor kernel {name} failed with status {status}")


@functools.cache
def _function(name: str, dtype: np.dtype) -> Callable[..., int]:
    library = _library()
    assert library is not None
    return getattr(library, f"{name}_{_TYPES[dtype]}")
