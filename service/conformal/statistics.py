"""Per-heatmap statistics shared by the three nonconformity functions (paper, Sec. 3): the peak q*
(centre of the argmax pixel) and p*; over the top-K pixels, weights renormalized to sum 1, the mean
q_bar, gamma^2 = sum w ||q - q_bar||^2 and Sigma = sum w (q - q_bar)(q - q_bar)^T. Pixel (row r,
col c) has centre (c + 0.5, r + 0.5); points are (x, y).

Regularization, identical in calibration and prediction: Sigma gets the smallest ridge lifting its
smallest eigenvalue to 1/12 px^2 (the variance of a point uniform over one pixel: a heatmap cannot
locate more finely than its grid), gamma^2 is floored at 2/12 px^2; real spreads are unchanged.
Uninformative maps (degenerate or flat) get a uniform distribution's statistics: centre (W/2, H/2),
p* = 1/(H*W), Sigma = diag(W^2/12, H^2/12): the largest set, never NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .anchor import raw_top_k
from .normalization import as_raw_batch, normalized_weights
from .selection import top_k_indices

PIXEL_VARIANCE = 1.0 / 12.0
DEFAULT_TOP_K = 100
_MIN_RAW_WIDTH = 1024  # smaller maps: the float64 path is cheap


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
    """Statistics of a raw (N, H, W) heatmap batch (float32 or float64) after normalization."""
    heatmaps = as_raw_batch(heatmaps)
    height, width = heatmaps.shape[1:]
    if not isinstance(top_k, int | np.integer) or top_k < 1:
        raise ValueError(f"top_k must be a positive integer, got {top_k!r}")
    k = min(int(top_k), height * width)
    flat = heatmaps.reshape(heatmaps.shape[0], -1)
    parts = (k, width, include_peak, include_spread)
    raw = flat.shape[1] >= _MIN_RAW_WIDTH and not include_peak  # peak's median needs every weight
    if normalization == "anchor" and raw and 2 * k <= flat.shape[1]:
        fields, uninformative = _raw_anchor_fields(flat, *parts)
    else:
        fields, uninformative = _weight_fields(flat.astype(np.float64), normalization, temperature, *parts)
    _use_uniform_statistics(fields, uninformative, height, width)
    return HeatmapStatistics((height, width), uninformative, **fields)


def pixel_centers(flat_indices: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) centres of row-major flat pixel indices."""
    rows, columns = np.divmod(flat_indices, width)
    return columns + 0.5, rows + 0.5


def _weight_fields(
    flat: np.ndarray, normalization: str, temperature: float, k: int, width: int, peak: bool, spread: bool
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The exact path: float64 weights of the whole batch (every mode)."""
    skip_median = normalization == "anchor" and not peak and 2 * k <= flat.shape[1]
    normalized = normalized_weights(flat, normalization, temperature, skip_anchor_median=skip_median)
    weights = normalized.weights
    uninformative = normalized.degenerate | (weights.max(axis=1) == weights.min(axis=1))
    fields: dict[str, np.ndarray] = {}
    if peak:
        argmax = weights.argmax(axis=1)
        peak_weight = weights[np.arange(weights.shape[0]), argmax]
        x, y = pixel_centers(argmax, width)
        fields.update(
            peak_location=np.stack([x, y], axis=1), peak_probability=peak_weight / normalized.totals
        )
    if spread:
        indices = top_k_indices(weights, k)
        fields.update(_spread(indices, np.take_along_axis(weights, indices, axis=1), width))
    return fields, uninformative


def _raw_anchor_fields(
    flat: np.ndarray, k: int, width: int, peak: bool, spread: bool
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """``anchor``'s top-K selected on the raw values (see ``anchor``); rows whose selection
    rounding could change go exact."""
    minimum, maximum = _extremes(flat)
    finite = np.isfinite(minimum) & np.isfinite(maximum)
    if not finite.all():  # degenerate rows: uniform statistics; zeros keep numpy quiet
        flat = np.where(finite[:, None], flat, 0)
        minimum, maximum = _extremes(flat)
    span = maximum - minimum
    uninformative = ~finite | (span == 0)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        exact = ~np.isfinite(span * (2 * flat.shape[1]))  # float64 weights could overflow
        fields: dict[str, np.ndarray] = {}
        if spread:
            indices, top_weights, ok = raw_top_k(flat, k, minimum)
            exact |= ~ok
            fields.update(_spread(indices, top_weights, width))
    exact &= ~uninformative
    if exact.any():
        rows = np.flatnonzero(exact)
        exact_fields, uninformative[rows] = _weight_fields(
            flat[rows].astype(np.float64), "anchor", 1.0, k, width, peak, spread
        )
        for name, value in exact_fields.items():
            fields[name][rows] = value
    return fields, uninformative


def _extremes(flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """numpy's min and max of each row, float64 (NaN where a row holds a NaN)."""
    return flat.min(axis=1).astype(np.float64), flat.max(axis=1).astype(np.float64)


def _spread(indices: np.ndarray, top_weights: np.ndarray, width: int) -> dict[str, np.ndarray]:
    """Mean and covariance of the pixel centres of ``indices`` (N, k, ascending) under the weights."""
    probabilities = top_weights / top_weights.sum(axis=-1)[:, None]
    x, y = pixel_centers(indices, width)
    mean_x, mean_y = np.stack([probabilities * x, probabilities * y]).sum(axis=-1)
    dx, dy = x - mean_x[:, None], y - mean_y[:, None]
    weighted_dx, weighted_dy = probabilities * dx, probabilities * dy
    sxx, sxy, syy = np.stack([weighted_dx * dx, weighted_dx * dy, weighted_dy * dy]).sum(axis=-1)
    covariance = np.stack([sxx, sxy, sxy, syy], axis=1).reshape(-1, 2, 2)
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
    adjugate = np.empty_like(matrices)
    adjugate[:, 0, 0], adjugate[:, 1, 1] = c, a
    adjugate[:, 0, 1] = adjugate[:, 1, 0] = -b
    return adjugate / determinant[:, None, None]
