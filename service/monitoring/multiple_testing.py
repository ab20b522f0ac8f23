"""Holm's step-down correction (Holm 1979), shared by coverage audits and the drift alarm: it controls
the family-wise error rate at alpha under any dependence between the tests.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def holm_adjusted(p_values: Sequence[float] | np.ndarray) -> np.ndarray:
    """Holm's adjusted p-values; NaN (tests not run) stay NaN, not counted."""
    p_values = np.asarray(p_values, dtype=np.float64)
    adjusted = np.full(p_values.shape, np.nan)
    flat = p_values.ravel()
    tested = np.flatnonzero(~np.isnan(flat))
    order = tested[np.argsort(flat[tested], kind="stable")]
    scaled = np.minimum(1.0, (order.size - np.arange(order.size)) * flat[order])
    adjusted.ravel()[order] = np.maximum.accumulate(scaled) if order.size else scaled
    return adjusted


def holm_rejections(p_values: Sequence[float] | np.ndarray, alpha: float) -> np.ndarray:
    adjusted = holm_adjusted(p_values)
    return ~np.isnan(adjusted) & (adjusted <= alpha)
