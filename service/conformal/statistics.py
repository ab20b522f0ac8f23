"""Per-heatmap statistics shared by the three nonconformity functions (paper, Sec. 3): the peak
q* (centre of the argmax pixel) and p* = f(x)_pi(1); over the top-K pixels with weights
renormalized to 1, the mean q_bar, variance gamma^2 = sum w ||q - q_bar||^2 and covariance Sigma.

Regularization, the same for calibration and sets: Sigma gets the smallest ridge lifting its
smallest eigenvalue to 1/12 px^2, gamma^2 is floored at 2/12 px^2. 1/12 is the variance of a point
uniform over one pixel: a heatmap cannot locate finer than its grid, so a smaller spread is an
artefact (a single-pixel or collinear top-K) that would make Sigma singular; real spreads are
unchanged. Uninformative maps (degenerate or flat) get the statistics of a uniform distribution
over the heatmap (centre (W/2, H/2), p* = 1/(H*W), Sigma = diag(W^2/12, H^2/12)): never NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .anchor import raw_top_k
from .kernel import anchor_peaks, native_kernel_available, top_k_spread
from .normalization import as_raw_batch, normalized_weights
from .selection import top_k_indices

PIXEL_VARIANCE = 1.0 / 12.0
DEFAULT_TOP_K = 100
_MIN_RAW_WIDTH = 1024  # smaller maps without the native kernel: the float64 path is cheap
_SUM_LANES = 8  # SUM_LANES of native/upper_half.c: the spread's summation order


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
    raw = flat.shape[1] >= _MIN_RAW_WIDTH or native_kernel_available()
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
        fields.update(_peak(argmax, peak_weight / normalized.totals, width))
    if spread:
        indices = top_k_indices(weights, k)
        fields.update(_spread(indices, np.take_along_axis(weights, indices, axis=1), width))
    return fields, uninformative


def _raw_anchor_fields(
    flat: np.ndarray, k: int, width: int, peak: bool, spread: bool
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """``anchor`` selected on the raw values (see ``anchor``); unsettled rows go exact: with the
    native kernel none but overflowing ones, without it every ``peak`` row and the top-K rows
    whose selection rounding could change."""
    peaks = anchor_peaks(flat) if peak else None
    top = top_k_spread(flat, k, width) if spread else None
    native = peaks if peaks is not None else top
    if native is not None:
        minimum, maximum = native.minimum, native.maximum
    else:
        minimum, maximum = _extremes(flat)
    finite = np.isfinite(minimum) & np.isfinite(maximum)
    if native is None and not finite.all():  # degenerate rows: uniform statistics; zeros keep numpy quiet
        flat = np.where(finite[:, None], flat, 0)
        minimum, maximum = _extremes(flat)
    span = maximum - minimum
    uninformative = ~finite | (span == 0)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        exact = ~np.isfinite(span * (2 * flat.shape[1]))  # float64 weights could overflow
        fields: dict[str, np.ndarray] = {}
        if peaks is not None:
            fields.update(_peak(peaks.argmax, span / peaks.sums, width))
        elif peak:  # no native kernel: every row takes the exact path
            exact[:] = True
            fields.update(_peak(np.zeros(flat.shape[0], np.intp), np.full(flat.shape[0], np.nan), width))
        if top is not None:
            fields.update(_spread_fields(top.spread))
        elif spread:
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


def _peak(argmax: np.ndarray, probability: np.ndarray, width: int) -> dict[str, np.ndarray]:
    x, y = pixel_centers(argmax, width)
    return {"peak_location": np.stack([x, y], axis=1), "peak_probability": probability}


def _spread(indices: np.ndarray, top_weights: np.ndarray, width: int) -> dict[str, np.ndarray]:
    """Mean and covariance of the pixel centres of ``indices`` (N, k, ascending) under the weights,
    every term and sum formed as ``kernel.top_k_spread`` forms it: the same bits."""
    probabilities = top_weights / _lane_sums(top_weights)[:, None]
    x, y = pixel_centers(indices, width)
    mean_x, mean_y = _lane_sums(np.stack([probabilities * x, probabilities * y]))
    dx, dy = x - mean_x[:, None], y - mean_y[:, None]
    weighted_dx, weighted_dy = probabilities * dx, probabilities * dy
    sxx, sxy, syy = _lane_sums(np.stack([weighted_dx * dx, weighted_dx * dy, weighted_dy * dy]))
    return _spread_fields(np.stack([mean_x, mean_y, sxx, sxy, syy], axis=1))


def _spread_fields(spread: np.ndarray) -> dict[str, np.ndarray]:
    """Mean (N, 2) and covariance (N, 2, 2) from the columns (mean x, mean y, Sxx, Sxy, Syy)."""
    return {"mean": spread[:, :2].copy(), "covariance": spread[:, [2, 3, 3, 4]].reshape(-1, 2, 2)}


def _lane_sums(terms: np.ndarray) -> np.ndarray:
    """Sums over the last axis in the native kernel's order (``sum_lanes``): term j goes to lane
    j % 8, each lane adds its terms in order to +0.0, and the lanes combine as ((l0 + l4) + (l2 +
    l6)) + ((l1 + l5) + (l3 + l7)). The +0.0 padding changes no lane."""
    *outer, count = terms.shape
    chunks = -(-count // _SUM_LANES) + 1  # one leading chunk of zeros: the lanes' start
    padded = np.zeros((*outer, chunks * _SUM_LANES))
    padded[..., _SUM_LANES : _SUM_LANES + count] = terms
    lanes = np.add.accumulate(padded.reshape(*outer, chunks, _SUM_LANES), axis=-2)[..., -1, :]
    pairs = lanes[..., :4] + lanes[..., 4:]
    pairs = pairs[..., :2] + pairs[..., 2:]
    return pairs[..., 0] + pairs[..., 1]


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
