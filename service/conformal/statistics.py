"""Per-heatmap statistics shared by the three nonconformity functions (paper, Sec. 3).

- peak: q* (centre of the argmax pixel) and p* = f(x)_pi(1);
- spread: over the top-K pixels with weights renormalized to sum to 1, the
  mean q_bar, the variance gamma^2 = sum w ||q - q_bar||^2 and the covariance
  Sigma = sum w (q - q_bar)(q - q_bar)^T.

Pixel (row r, col c) has centre (c + 0.5, r + 0.5); points are (x, y).

Regularization, applied identically when scoring calibration data and when
building sets: Sigma gets the smallest ridge that lifts its smallest eigenvalue
to 1/12 px^2, and gamma^2 is floored at 2/12 px^2. 1/12 is the variance of a
point uniform over one pixel: a heatmap cannot locate a keypoint more finely
than its grid, so a smaller spread is an artefact (a single-pixel or
collinear top-K) that would make Sigma singular and gamma zero. Real spreads
(several pixels) are left bit-for-bit unchanged.

Uninformative maps (degenerate after normalization, or flat) get the statistics
of a uniform distribution over the whole heatmap: centre (W/2, H/2),
p* = 1/(H*W), Sigma = diag(W^2/12, H^2/12). The set is then centred and as
large as the heatmap allows, never NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .normalization import as_heatmap_batch, normalized_weights
from .selection import top_k_indices

PIXEL_VARIANCE = 1.0 / 12.0
DEFAULT_TOP_K = 100


@dataclass(frozen=True)
class HeatmapStatistics:
    """Vectorized statistics of N heatmaps of shape (H, W); unrequested parts are None."""

    heatmap_shape: tuple[int, int]
    uninformative: np.ndarray  # (N,) bool: degenerate or flat map, uniform statistics used
    peak_location: np.ndarray | None = None  # (N, 2) q*
    peak_probability: np.ndarray | None = None  # (N,) p*
    mean: np.ndarray | None = None  # (N, 2) q_bar
    covariance: np.ndarray | None = None  # (N, 2, 2) Sigma, before regularization

    @property
    def variance(self) -> np.ndarray:
        """gamma^2 = trace(Sigma), before regularization (eq. Var)."""
        return np.trace(self._require("covariance"), axis1=1, axis2=2)

    @property
    def regularized_variance(self) -> np.ndarray:
        return np.maximum(self.variance, 2 * PIXEL_VARIANCE)

    @property
    def regularized_covariance(self) -> np.ndarray:
        covariance = self._require("covariance")
        ridge = np.maximum(PIXEL_VARIANCE - _smallest_eigenvalue(covariance), 0.0)
        return covariance + ridge[:, None, None] * np.eye(2)

    @property
    def precision(self) -> np.ndarray:
        """Inverse of the regularized covariance, (N, 2, 2), in closed form."""
        return _inverse_2x2(self.regularized_covariance)

    def _require(self, name: str) -> np.ndarray:
        value = getattr(self, name)
        if value is None:
            raise ValueError(f"{name} was not computed; request it in heatmap_statistics")
        return value


def heatmap_statistics(
    heatmaps: np.ndarray,
    normalization: str = "anchor",
    top_k: int = DEFAULT_TOP_K,
    temperature: float = 1.0,
    *,
    include_peak: bool = True,
    include_spread: bool = True,
) -> HeatmapStatistics:
    """Statistics of a raw (N, H, W) heatmap batch after normalization."""
    heatmaps = as_heatmap_batch(heatmaps)
    height, width = heatmaps.shape[1:]
    if not isinstance(top_k, int | np.integer) or top_k < 1:
        raise ValueError(f"top_k must be a positive integer, got {top_k!r}")
    k = min(int(top_k), height * width)
    skip_median = normalization == "anchor" and not include_peak and 2 * k <= height * width
    normalized = normalized_weights(heatmaps, normalization, temperature, skip_anchor_median=skip_median)
    weights = normalized.weights
    uninformative = normalized.degenerate | (weights.max(axis=1) == weights.min(axis=1))
    fields: dict[str, np.ndarray] = {}
    if include_peak:
        fields.update(_peak(weights, normalized.totals, width))
    if include_spread:
        fields.update(_spread(weights, k, width))
    _use_uniform_statistics(fields, uninformative, height, width)
    return HeatmapStatistics((height, width), uninformative, **fields)


def pixel_centers(flat_indices: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) centres of row-major flat pixel indices."""
    rows, columns = np.divmod(flat_indices, width)
    return columns + 0.5, rows + 0.5


def _peak(weights: np.ndarray, totals: np.ndarray, width: int) -> dict[str, np.ndarray]:
    argmax = weights.argmax(axis=1)
    x, y = pixel_centers(argmax, width)
    peak_weight = weights[np.arange(weights.shape[0]), argmax]
    return {"peak_location": np.stack([x, y], axis=1), "peak_probability": peak_weight / totals}


def _spread(weights: np.ndarray, k: int, width: int) -> dict[str, np.ndarray]:
    indices = top_k_indices(weights, k)
    top_weights = np.take_along_axis(weights, indices, axis=1)
    top_weights /= top_weights.sum(axis=1, keepdims=True)
    x, y = pixel_centers(indices, width)
    mean_x = np.einsum("nk,nk->n", top_weights, x)
    mean_y = np.einsum("nk,nk->n", top_weights, y)
    dx, dy = x - mean_x[:, None], y - mean_y[:, None]
    sxx = np.einsum("nk,nk,nk->n", top_weights, dx, dx)
    syy = np.einsum("nk,nk,nk->n", top_weights, dy, dy)
    sxy = np.einsum("nk,nk,nk->n", top_weights, dx, dy)
    covariance = np.stack([np.stack([sxx, sxy], -1), np.stack([sxy, syy], -1)], -2)
    return {"mean": np.stack([mean_x, mean_y], axis=1), "covariance": covariance}


def _use_uniform_statistics(
    fields: dict[str, np.ndarray], uninformative: np.ndarray, height: int, width: int
) -> None:
    if not uninformative.any():
        return
    center = np.array([width / 2, height / 2])
    uniform = {
        "peak_location": center,
        "mean": center,
        "peak_probability": 1.0 / (height * width),
        "covariance": np.diag([width**2 / 12, height**2 / 12]),
    }
    for name, value in fields.items():
        value[uninformative] = uniform[name]


def _smallest_eigenvalue(matrices: np.ndarray) -> np.ndarray:
    a, b, c = matrices[:, 0, 0], matrices[:, 0, 1], matrices[:, 1, 1]
    return (a + c) / 2 - np.hypot((a - c) / 2, b)


def _inverse_2x2(matrices: np.ndarray) -> np.ndarray:
    a, b, c = matrices[:, 0, 0], matrices[:, 0, 1], matrices[:, 1, 1]
    determinant = a * c - b * b
    inverse = np.stack([np.stack([c, -b], -1), np.stack([-b, a], -1)], -2)
    return inverse / determinant[:, None, None]
