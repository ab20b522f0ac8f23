"""An independent, deliberately plain implementation of the paper's formulas.

One heatmap at a time, full sort, np.linalg.inv: the way the authors' code reads.
Tie-breaking (stable sort, lowest row-major index first), the 1/12 px^2
regularization and the uniform fallback are the documented rules of
service.conformal.statistics, restated here from their definitions.
"""

from __future__ import annotations

import numpy as np

PIXEL_VARIANCE = 1.0 / 12.0


def normalize(heatmap: np.ndarray, mode: str = "anchor") -> np.ndarray | None:
    """Probability map, or None for a degenerate map."""
    if not np.all(np.isfinite(heatmap)):
        return None
    if mode == "anchor":
        heatmap = heatmap - np.min(heatmap)
        heatmap[heatmap < np.median(heatmap)] = 0
    elif mode == "relu":
        heatmap = np.maximum(heatmap, 0)
    elif mode == "softmax":
        heatmap = np.exp(heatmap - heatmap.max())
    total = heatmap.sum()
    if not total > 0 or heatmap.max() == heatmap.min():
        return None
    return heatmap / total


def statistics(heatmap: np.ndarray, mode: str = "anchor", k: int = 100) -> dict:
    height, width = heatmap.shape
    probability = normalize(heatmap, mode)
    if probability is None:
        center = np.array([width / 2, height / 2])
        sigma = np.diag([width**2 / 12, height**2 / 12])
        return {"q_star": center, "p_star": 1 / (height * width), "q_bar": center, "sigma": sigma}
    flat = probability.ravel()
    order = np.argsort(-flat, kind="stable")
    rows, cols = np.unravel_index(order, probability.shape)
    points = np.stack([cols + 0.5, rows + 0.5], axis=1)
    weights = flat[order][:k] / flat[order][:k].sum()
    q_bar = weights @ points[:k]
    diff = points[:k] - q_bar
    sigma = diff.T @ np.diag(weights) @ diff
    return {"q_star": points[0], "p_star": flat[order[0]], "q_bar": q_bar, "sigma": sigma}


def regularized(sigma: np.ndarray) -> np.ndarray:
    smallest = np.linalg.eigvalsh(sigma)[0]
    return sigma + max(0.0, PIXEL_VARIANCE - smallest) * np.eye(2)


def score(kind: str, heatmap: np.ndarray, keypoint: np.ndarray, mode: str = "anchor", k=100):
    s = statistics(heatmap, mode, k)
    if kind == "peak":
        return s["p_star"] * np.linalg.norm(keypoint - s["q_star"])
    if kind == "var":
        gamma = np.sqrt(max(np.trace(s["sigma"]), 2 * PIXEL_VARIANCE))
        return np.linalg.norm(keypoint - s["q_bar"]) / gamma
    d = keypoint - s["q_bar"]
    return d @ np.linalg.inv(regularized(s["sigma"])) @ d


def region(kind: str, heatmap: np.ndarray, threshold: float, mode: str = "anchor", k=100):
    """Centre and shape matrix L of the ICP set, (y - c)^T L (y - c) <= 1."""
    s = statistics(heatmap, mode, k)
    if kind == "peak":
        radius = threshold / s["p_star"]
        return s["q_star"], np.eye(2) / radius**2
    if kind == "var":
        radius = np.sqrt(max(np.trace(s["sigma"]), 2 * PIXEL_VARIANCE)) * threshold
        return s["q_bar"], np.eye(2) / radius**2
    return s["q_bar"], np.linalg.inv(regularized(s["sigma"])) / threshold
