"""Conformal keypoint core: numpy, no I/O, vectorized over a batch of heatmaps.

Implements "Conformal Semantic Keypoint Detection with Statistical Guarantees"
(Yang & Pavone); see DESIGN.md, "Numerics contract". Heatmap coordinates: pixel
(row r, col c) has centre (c + 0.5, r + 0.5); points are (x, y).

Stable entry points
-------------------
``nonconformity_scores(kind, heatmaps, keypoints, normalization="anchor", top_k=100)``
    (N,) scores of labelled keypoints; kind is "peak", "var" or "cov".
``conformal_threshold(scores, epsilon)``
    alpha_(floor((n+1) eps)) of eq. (3); ``math.inf`` (unbounded) when t = 0.
``prediction_sets(kind, heatmaps, threshold, normalization="anchor", top_k=100)``
    centres (N, 2) and shapes L (N, 2, 2) with (y - c)^T L (y - c) <= 1;
    threshold is a float or one per heatmap; unbounded -> L = 0.
``point_estimates(kind, heatmaps, ...)``
    argmax centre (peak) or top-K weighted mean (var, cov).

Building blocks
---------------
Normalization  ``normalize_heatmaps(heatmaps, mode="anchor", temperature=1.0)``;
               modes in ``NORMALIZATION_MODES``; degenerate maps become uniform.
Statistics     ``heatmap_statistics(...) -> HeatmapStatistics`` (q*, p*, q_bar,
               Sigma, gamma^2 and their regularized forms; see ``statistics``
               for the 1/12 px^2 floor).
Scores         ``PeakScore``, ``VarScore``, ``CovScore`` (``score`` / ``region`` /
               ``point_estimate``), ``NONCONFORMITY_SCORES`` registry,
               ``get_nonconformity_score(kind)``.
Thresholds     ``conformal_rank(n, eps)`` (float-safe floor), ``threshold_for_rank``,
               ``column_thresholds`` (per keypoint, NaN = unlabeled),
               ``object_scores`` (max over an object's keypoints).
Guarantees     ``calibrate(scores, eps, delta=None) -> Calibration(threshold,
               guarantee)``, ``calibrate_columns``, ``coverage_guarantee``,
               ``CoverageGuarantee`` (n, t, marginal bounds, Beta(n+1-t, t),
               PAC failure probability), ``pac_rank``, ``beta_cdf``, ``binomial_cdf``.
Geometry       ``map_sets_to_image(centers, shapes, affine)`` (image->heatmap 2x3
               affine; L -> M^T L M), ``contains``, ``ellipse_axes`` (a <= b,
               angle in degrees), ``ball_shapes``, ``ball_radii``.
"""

from .entry_points import nonconformity_scores, point_estimates, prediction_sets, statistics_for
from .features import HEATMAP_FEATURES, heatmap_features
from .geometry import ball_radii, ball_shapes, contains, ellipse_axes, map_sets_to_image
from .guarantees import (
    Calibration,
    CoverageGuarantee,
    beta_cdf,
    binomial_cdf,
    calibrate,
    calibrate_columns,
    coverage_guarantee,
    pac_rank,
)
from .normalization import NORMALIZATION_MODES, normalize_heatmaps
from .scores import (
    NONCONFORMITY_SCORES,
    CovScore,
    NonconformityScore,
    PeakScore,
    VarScore,
    get_nonconformity_score,
)
from .statistics import PIXEL_VARIANCE, HeatmapStatistics, heatmap_statistics
from .threshold import (
    column_thresholds,
    conformal_rank,
    conformal_threshold,
    object_scores,
    threshold_for_rank,
)

__all__ = [
    "HEATMAP_FEATURES",
    "heatmap_features",
    "NONCONFORMITY_SCORES",
    "NORMALIZATION_MODES",
    "PIXEL_VARIANCE",
    "Calibration",
    "CovScore",
    "CoverageGuarantee",
    "HeatmapStatistics",
    "NonconformityScore",
    "PeakScore",
    "VarScore",
    "ball_radii",
    "ball_shapes",
    "beta_cdf",
    "binomial_cdf",
    "calibrate",
    "calibrate_columns",
    "column_thresholds",
    "conformal_rank",
    "conformal_threshold",
    "contains",
    "coverage_guarantee",
    "ellipse_axes",
    "get_nonconformity_score",
    "heatmap_statistics",
    "map_sets_to_image",
    "normalize_heatmaps",
    "nonconformity_scores",
    "object_scores",
    "pac_rank",
    "point_estimates",
    "prediction_sets",
    "statistics_for",
    "threshold_for_rank",
]
