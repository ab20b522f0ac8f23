"""Label-free features of each keypoint's heatmap, computed the same way at calibration and
at prediction.

They describe how hard a keypoint is for the model without knowing where it truly is:
p* (the normalized peak probability; low when the model is unsure), gamma (the top-K
spread of eq. Var, in heatmap pixels; large when the mass is diffuse) and the anisotropy
of the top-K covariance (large when the mass is elongated, e.g. along an occluding edge).
Stored with every calibration version, they are the reference distribution of the drift
monitor and the difficulty signal of Mondrian strata.
"""

from __future__ import annotations

import numpy as np

from .statistics import HeatmapStatistics

HEATMAP_FEATURES: tuple[str, ...] = ("peak_probability", "gamma", "anisotropy")


def heatmap_features(statistics: HeatmapStatistics) -> dict[str, np.ndarray]:
    """Each of HEATMAP_FEATURES as an (N,) float64 array; needs peak and spread statistics."""
    eigenvalues = np.linalg.eigvalsh(statistics.regularized_covariance)  # ascending, > 0
    return {
        "peak_probability": np.asarray(statistics.peak_probability, dtype=np.float64),
        "gamma": np.sqrt(statistics.variance),
        "anisotropy": np.sqrt(eigenvalues[:, 1] / eigenvalues[:, 0]),
    }
