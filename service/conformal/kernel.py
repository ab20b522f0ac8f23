"""The native anchor-median kernel (``native/upper_half.c``), loaded with ctypes.

``peak`` needs, per heatmap, S = the sum of the anchor weights at or above
their median, i.e. an exact median of 4096 values. numpy's fastest exact tool,
``np.partition``, costs about as much per map as the whole per-heatmap
reference loop. The kernel selects the two middle values by vectorized counting
passes instead (``python -m benchmarks.bench_conformal`` prints the figures).

It is built by ``pip install`` when a C compiler is present (an optional
extension: no compiler, no failure). Without it, ``upper_half_sums`` returns
None and callers take the exact numpy path, which gives the same numbers.
"""

from __future__ import annotations

import ctypes
import functools
from pathlib import Path

import numpy as np

_LIBRARY = "_upper_half"
_VERSION = 2  # cks_kernel_version() of the sources this module expects
_FUNCTIONS = {
    np.dtype(np.float32): "cks_upper_half_sums_f32",
    np.dtype(np.float64): "cks_upper_half_sums_f64",
}
_MAX_WIDTH = 2**31 - 1  # the kernel counts in 32-bit lanes


@functools.cache
def _library() -> ctypes.CDLL | None:
    try:
        library = np.ctypeslib.load_library(_LIBRARY, Path(__file__).parent)
        current = library.cks_kernel_version() == _VERSION
    except (OSError, AttributeError):  # not built, or a build of older sources
        return None
    return library if current else None


def native_kernel_available() -> bool:
    """True when the compiled kernel was built and loads."""
    return _library() is not None


def upper_half_sums(flat: np.ndarray, minimum: np.ndarray, maximum: np.ndarray) -> np.ndarray | None:
    """S (N,) per row of finite raw values (N, M), M >= 2; None without the kernel.

    ``minimum`` and ``maximum`` are the rows' extremes as float64. S is the sum
    of w = float64(v) - minimum over the w >= median(w) (np.median's median),
    summed in another order than numpy's (a few ulp apart).
    """
    library = _library()
    supported = flat.ndim == 2 and flat.dtype in _FUNCTIONS and 2 <= flat.shape[1] <= _MAX_WIDTH
    if library is None or not supported:
        return None
    if np.shape(minimum) != (flat.shape[0],) or np.shape(maximum) != (flat.shape[0],):
        raise ValueError(f"minimum and maximum need one value per row, {flat.shape[0]} rows")
    flat = np.require(flat, requirements="CA")  # C order, aligned, native byte order
    minimum = np.require(minimum, np.float64, "CA")
    maximum = np.require(maximum, np.float64, "CA")
    sums = np.empty(flat.shape[0], dtype=np.float64)
    status = getattr(library, _FUNCTIONS[flat.dtype])(
        _pointer(flat), ctypes.c_int64(flat.shape[0]), ctypes.c_int64(flat.shape[1]),
        _pointer(minimum), _pointer(maximum), _pointer(sums),
    )
    if status != 0:
        raise RuntimeError(f"native anchor kernel failed with status {status}")
    return sums


def _pointer(array: np.ndarray) -> ctypes.c_void_p:
    return ctypes.c_void_p(array.ctypes.data)
