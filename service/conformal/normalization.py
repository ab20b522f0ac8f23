"""Heatmap normalization: raw detector output -> probability map f(x) over the H*W pixels.

Modes: ``anchor`` (the reference ``clean_heatmap``: subtract the minimum, zero below the median,
divide by the sum), ``softmax`` and ``relu``. A degenerate map (normalizer zero or not finite)
becomes uniform 1/(H*W), the least informative answer; never NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NORMALIZATION_MODES = ("anchor", "softmax", "relu")


@dataclass(frozen=True)
class NormalizedHeatmaps:
    """Nonnegative weights (N, P), probabilities weights / totals; ``degenerate``: uniform maps."""

    weights: np.ndarray
    totals: np.ndarray
    degenerate: np.ndarray

    def probabilities(self) -> np.ndarray:
        return self.weights / self.totals[:, None]


def normalize_heatmaps(heatmaps: np.ndarray, mode: str = "anchor", temperature: float = 1.0) -> np.ndarray:
    """Probability maps (N, H, W) float64, each summing to 1, from raw heatmaps (N, H, W)."""
    heatmaps = _checked_shape(np.asarray(heatmaps, dtype=np.float64))
    return normalized_weights(heatmaps, mode, temperature).probabilities().reshape(heatmaps.shape)


def as_raw_batch(heatmaps: np.ndarray) -> np.ndarray:
    """Validate a (N, H, W) batch; float32 and float64 are kept, anything else becomes float64."""
    heatmaps = np.asarray(heatmaps)
    if heatmaps.dtype not in (np.float32, np.float64):
        heatmaps = heatmaps.astype(np.float64)
    return _checked_shape(heatmaps)


def _checked_shape(heatmaps: np.ndarray) -> np.ndarray:
    if heatmaps.ndim != 3 or heatmaps.shape[1] == 0 or heatmaps.shape[2] == 0:
        raise ValueError(f"heatmaps must have shape (N, H, W) with H, W >= 1, got {heatmaps.shape}")
    return heatmaps


def normalized_weights(
    heatmaps: np.ndarray, mode: str = "anchor", temperature: float = 1.0, *, skip_anchor_median: bool = False
) -> NormalizedHeatmaps:
    """Nonnegative weights and their totals for a (N, H, W) batch. ``skip_anchor_median`` keeps
    ``anchor``'s below-median values: only for callers renormalizing the top K <= H*W/2 weights."""
    flat = heatmaps.reshape(heatmaps.shape[0], -1)
    finite = np.isfinite(flat).all(axis=1)
    if not finite.all():
        flat = np.where(finite[:, None], flat, 0.0)
    if mode == "anchor":
        weights = _anchor(flat, with_median=not skip_anchor_median)
    elif mode == "softmax":
        weights = _softmax(flat, temperature)
    elif mode == "relu":
        weights = np.maximum(flat, 0.0)
    else:
        raise ValueError(f"unknown normalization {mode!r}; expected one of {NORMALIZATION_MODES}")
    with np.errstate(over="ignore", invalid="ignore"):  # overflow -> inf -> degenerate
        totals = weights.sum(axis=1)
    degenerate = ~finite | ~np.isfinite(totals) | (totals <= 0)
    weights[degenerate] = 1.0
    totals[degenerate] = flat.shape[1]
    return NormalizedHeatmaps(weights, totals, degenerate)


def _anchor(flat: np.ndarray, with_median: bool) -> np.ndarray:
    weights = flat - flat.min(axis=1, keepdims=True)
    if with_median:
        median = np.median(weights, axis=1, keepdims=True)
        np.multiply(weights, weights >= median, out=weights)  # zero below the median
    return weights


def _softmax(flat: np.ndarray, temperature: float) -> np.ndarray:
    if not (np.isfinite(temperature) and temperature > 0):
        raise ValueError(f"softmax temperature must be a positive finite number, got {temperature}")
    with np.errstate(over="ignore", invalid="ignore"):
        scaled = flat / temperature
        return np.exp(scaled - scaled.max(axis=1, keepdims=True))
