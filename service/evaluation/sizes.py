"""Tightness (the paper's Fig. 3): set sizes in image pixels, balls by their radius, ellipses by their
semi-axes a <= b, areas pi r^2 and pi a b; unbounded sets (t = 0) stay in the medians as infinite."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.conformal import ball_radii, ellipse_axes


@dataclass(frozen=True)
class SetSizes:
    """Per row: semi-axes a <= b (a = b = r for balls) and area, image pixels."""

    a: np.ndarray
    b: np.ndarray

    @property
    def area(self) -> np.ndarray:
        return np.pi * self.a * self.b

    def median(self, values: np.ndarray) -> float:
        return float(np.median(values)) if values.size else float("nan")


def set_sizes(kind: str, shapes: np.ndarray) -> SetSizes:
    """Radii of balls (peak, var) or semi-axes of ellipses (cov), from image-space shapes."""
    if kind == "cov":
        a, b, _ = ellipse_axes(shapes)
        return SetSizes(a, b)
    radii = ball_radii(shapes)
    return SetSizes(radii, radii)


def empirical_cdf(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted values and their CDF levels i/n, for a step plot."""
    x = np.sort(values)
    return x, np.arange(1, x.size + 1) / max(x.size, 1)
