"""Procedural textures (numpy only, nothing downloaded) for the ground and the background."""

from __future__ import annotations

import cv2
import numpy as np


def smooth_noise(rng: np.random.Generator, size: tuple[int, int], cells: int) -> np.ndarray:
    """``(H, W)`` noise in [0, 1] made by upsampling a ``cells x cells`` random grid."""
    grid = rng.random((cells, cells)).astype(np.float32)
    return cv2.resize(grid, (size[1], size[0]), interpolation=cv2.INTER_CUBIC).clip(0, 1)


def _palette(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    return rng.uniform(0, 255, 3), rng.uniform(0, 255, 3)


def _pattern(rng: np.random.Generator, size: tuple[int, int]) -> np.ndarray:
    """A scalar pattern in [0, 1]: noise, checker, stripes or wood-like rings."""
    h, w = size
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    kind = rng.integers(4)
    if kind == 0:
        return 0.6 * smooth_noise(rng, size, int(rng.integers(3, 12))) + 0.4 * smooth_noise(rng, size, 48)
    if kind == 1:
        period = float(rng.uniform(8, 64))
        return (((xx // period) + (yy // period)) % 2).astype(np.float32)
    if kind == 2:
        angle = rng.uniform(0, np.pi)
        period = float(rng.uniform(6, 40))
        phase = (np.cos(angle) * xx + np.sin(angle) * yy) / period
        return (0.5 + 0.5 * np.sin(2 * np.pi * phase)).astype(np.float32)
    cx, cy = rng.uniform(-w, 2 * w), rng.uniform(-h, 2 * h)
    radius = np.hypot(xx - cx, yy - cy) + 20 * smooth_noise(rng, size, 6)
    return (0.5 + 0.5 * np.sin(radius / rng.uniform(3, 12))).astype(np.float32)


def texture(rng: np.random.Generator, size: tuple[int, int]) -> np.ndarray:
    """A random ``(H, W, 3)`` uint8 texture with two colours and a little grain."""
    a, b = _palette(rng)
    t = _pattern(rng, size)[:, :, None]
    image = a * (1 - t) + b * t + rng.normal(0, rng.uniform(0, 8), (*size, 1))
    return image.clip(0, 255).astype(np.uint8)
