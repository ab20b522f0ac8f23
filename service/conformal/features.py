"""Label-free features of each keypoint's heatmap, the same at calibration and prediction: p*,
gamma (the top-K spread) and the anisotropy of the top-K covariance. Stored with every version: the
drift monitor's reference and the difficulty signal of Mondrian strata.
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
