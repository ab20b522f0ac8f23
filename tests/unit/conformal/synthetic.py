"""Synthetic heatmaps for the conformal tests: random fields and Gaussian blobs."""

from __future__ import annotations

import numpy as np


def gaussian_blobs(
    rng: np.random.Generator, n: int, size: int = 64, noise: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Anisotropic Gaussian blobs (N, size, size) and their centres (N, 2) in (x, y)."""
    centers = rng.uniform(0.2 * size, 0.8 * size, (n, 2))
    sigmas = rng.uniform(0.8, size / 8, (n, 2))
    angles = rng.uniform(0, np.pi, n)
    grid = np.arange(size) + 0.5
    dx = grid[None, None, :] - centers[:, 0, None, None]
    dy = grid[None, :, None] - centers[:, 1, None, None]
    cos, sin = np.cos(angles)[:, None, None], np.sin(angles)[:, None, None]
    u, v = cos * dx + sin * dy, -sin * dx + cos * dy
    blobs = np.exp(-0.5 * ((u / sigmas[:, 0, None, None]) ** 2 + (v / sigmas[:, 1, None, None]) ** 2))
    return blobs + noise * rng.standard_normal(blobs.shape), centers


def random_fields(rng: np.random.Generator, n: int, size: int = 64) -> np.ndarray:
    """Unstructured random heatmaps with a random offset and scale."""
    return rng.normal(rng.normal(0, 3, (n, 1, 1)), rng.uniform(0.1, 5, (n, 1, 1)), (n, size, size))


def mixed_heatmaps(rng: np.random.Generator, n: int, size: int = 64) -> np.ndarray:
    """A mix of clean blobs, noisy blobs and random fields."""
    third = n // 3
    clean, _ = gaussian_blobs(rng, third, size)
    noisy, _ = gaussian_blobs(rng, third, size, noise=0.05)
    return np.concatenate([clean, noisy, random_fields(rng, n - 2 * third, size)])
