"""Conformal keypoint core: numpy, no I/O, vectorized over a batch of heatmaps.

Implements "Conformal Semantic Keypoint Detection with Statistical Guarantees" (Yang & Pavone); see
DESIGN.md, "Numerics contract". Pixel (row r, col c) has centre (c + 0.5, r + 0.5); points are (x, y).
"""

from .entry_points import nonconformity_scores, point_estimates, prediction_sets, statistics_for
from .features import HEATMAP_FEATURES, heatmap_features
from .geometry import ball_radii, ball_shapes, contains, ellipse_axes, map_sets_to_image
from .guarantees import (
    CoverageGuarantee,
    beta_cdf,
    binomial_cdf,
    calibrate,
    calibrate_columns,
    coverage_guarantee,
    pac_rank,
)
from .normalization import normalize_heatmaps
from .scores import NONCONFORMITY_SCORES, get_nonconformity_score
from .statistics import HeatmapStatistics, heatmap_statistics
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
    "CoverageGuarantee",
    "HeatmapStatistics",
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
