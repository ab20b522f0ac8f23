"""Set geometry: sets {y : (y - c)^T L (y - c) <= 1}, vectorized over N. L = 0 is the unbounded
set (whole plane), L = diag(inf, inf) the single point c, a ball of radius r has L = I / r^2.
"""

from __future__ import annotations

import numpy as np


def map_sets_to_image(
    centers: np.ndarray, shapes: np.ndarray, affine: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Map sets from heatmap to image coordinates through the image-to-heatmap affine [M | b]
    (one, or one per set): c_img = M^-1 (c - b) and, as y_hm - c = M (y_img - c_img), L -> M^T L M."""
    centers = np.asarray(centers, dtype=np.float64)
    shapes = np.asarray(shapes, dtype=np.float64)
    affine = np.broadcast_to(np.asarray(affine, dtype=np.float64), (centers.shape[0], 2, 3))
    linear, offset = affine[:, :, :2], affine[:, :, 2]
    if np.any(np.abs(np.linalg.det(linear)) <= 1e-12 * np.abs(linear).max(axis=(1, 2)) ** 2):
        raise ValueError("the affine's 2x2 part must be invertible")
    image_centers = np.linalg.solve(linear, (centers - offset)[..., None])[..., 0]
    with np.errstate(invalid="ignore"):
        image_shapes = np.einsum("nji,njk,nkl->nil", linear, shapes, linear)
    image_shapes[np.isinf(shapes).any(axis=(1, 2))] = np.diag([np.inf, np.inf])
    return image_centers, image_shapes


def contains(points: np.ndarray, centers: np.ndarray, shapes: np.ndarray) -> np.ndarray:
    """(N,) bool: is points[i] in set i? An unbounded set contains everything."""
    offsets = np.asarray(points, dtype=np.float64) - centers
    point_sets = np.isinf(shapes).any(axis=(1, 2))
    finite_shapes = np.where(point_sets[:, None, None], 0.0, shapes)
    quadratic = np.einsum("ni,nij,nj->n", offsets, finite_shapes, offsets)
    on_center = np.all(offsets == 0, axis=1)
    return np.where(point_sets, on_center, quadratic <= 1.0)


def ellipse_axes(shapes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Semi-axes a <= b (the eigenvalues of L are 1/a^2 >= 1/b^2; inf unbounded, 0 a point) and the
    angle in degrees, (-90, 90], of the b axis from +x towards +y (clockwise on screen, as
    matplotlib's Ellipse(angle=...) with width 2b, height 2a over an image; 0 for a circle)."""
    shapes = np.asarray(shapes, dtype=np.float64)
    p, q, r = shapes[:, 0, 0], shapes[:, 0, 1], shapes[:, 1, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        half_gap = np.hypot((p - r) / 2, q)
        large, small = (p + r) / 2 + half_gap, (p + r) / 2 - half_gap
        semi_minor = 1.0 / np.sqrt(large)
        semi_major = 1.0 / np.sqrt(np.maximum(small, 0.0))
        # the major axis is 90 degrees from the largest eigenvalue's, 0.5 * atan2(2q, p - r)
        angle = np.degrees(0.5 * np.arctan2(2 * q, p - r)) + 90.0
    angle = np.where(angle > 90.0, angle - 180.0, angle)
    is_point = np.isinf(shapes).any(axis=(1, 2))
    semi_minor, semi_major = np.where(is_point, 0.0, [semi_minor, semi_major])
    return semi_minor, semi_major, np.where((half_gap == 0) | is_point, 0.0, angle)


def ball_shapes(radii: np.ndarray) -> np.ndarray:
    """Shape matrices I / r^2 (N, 2, 2) of balls; r = inf -> 0, r = 0 -> diag(inf)."""
    radii = np.asarray(radii, dtype=np.float64)
    shapes = np.zeros((radii.shape[0], 2, 2))
    with np.errstate(divide="ignore"):
        shapes[:, 0, 0] = shapes[:, 1, 1] = 1.0 / radii**2
    return shapes


def ball_radii(shapes: np.ndarray) -> np.ndarray:
    """Radius of ball-shaped sets (L = I / r^2): 1/sqrt(L_00); inf when unbounded."""
    with np.errstate(divide="ignore"):
        return 1.0 / np.sqrt(np.asarray(shapes, dtype=np.float64)[:, 0, 0])
