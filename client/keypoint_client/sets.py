"""The geometry of prediction sets: membership, area and outline of a ball, an ellipse or the
whole plane, inherited by the generated BallSet, EllipseSet and UnboundedSet.

Coordinates are image pixels, x to the right and y down, with the origin at the top-left
corner of the top-left pixel (pixel (row r, column c) has its centre at (c + 0.5, r + 0.5)),
as in the API. ``contains`` and ``boundary`` need numpy (``pip install './client[numpy]'``).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from keypoint_client._numpy import np, require_numpy
from keypoint_client.bases import Frozen

if TYPE_CHECKING:
    from numpy.typing import ArrayLike, NDArray

Point = tuple[float, float]


def _offsets(points: ArrayLike, center: Point) -> NDArray[np.float64]:
    require_numpy("contains()")
    array = np.asarray(points, dtype=np.float64)
    if array.shape[-1:] != (2,):
        raise ValueError(f"points must be an (N, 2) array of (x, y) or one (x, y); got shape {array.shape}")
    return array - np.asarray(center, dtype=np.float64)


def _angles(n: int) -> NDArray[np.float64]:
    require_numpy("boundary()")
    if n < 3:
        raise ValueError(f"a boundary polygon needs at least 3 vertices, not {n}")
    return np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)


class BallGeometry(Frozen):
    """Every point within ``radius`` of ``center`` (radius 0: the single point ``center``)."""

    if TYPE_CHECKING:
        center: Point
        radius: float

    @property
    def area(self) -> float:
        return math.pi * self.radius**2

    def contains(self, points: ArrayLike) -> NDArray[np.bool_]:
        """For an (N, 2) array of (x, y), N booleans (for one (x, y), a 0-d array)."""
        offsets = _offsets(points, self.center)
        return np.asarray(np.hypot(offsets[..., 0], offsets[..., 1]) <= self.radius)

    def boundary(self, n: int = 64) -> NDArray[np.float64]:
        """The circle as an (n, 2) polygon of (x, y), from +x turning towards +y."""
        angles = _angles(n)
        return np.asarray(self.center) + self.radius * np.stack([np.cos(angles), np.sin(angles)], axis=1)


class EllipseGeometry(Frozen):
    """Every point y with (y - center)^T shape_matrix (y - center) <= 1."""

    if TYPE_CHECKING:
        center: Point
        shape_matrix: tuple[Point, Point]
        semi_axes: Point
        angle_deg: float

    @property
    def area(self) -> float:
        return math.pi * self.semi_axes[0] * self.semi_axes[1]

    def contains(self, points: ArrayLike) -> NDArray[np.bool_]:
        """For an (N, 2) array of (x, y), N booleans (for one (x, y), a 0-d array)."""
        offsets = _offsets(points, self.center)
        quadratic = np.einsum("...i,ij,...j->...", offsets, np.asarray(self.shape_matrix), offsets)
        return np.asarray(quadratic <= 1.0)

    def boundary(self, n: int = 64) -> NDArray[np.float64]:
        """The ellipse as an (n, 2) polygon of (x, y), starting at the end of the major axis."""
        angles = _angles(n)
        minor, major = self.semi_axes
        theta = math.radians(self.angle_deg)
        along = np.array([math.cos(theta), math.sin(theta)])
        across = np.array([-math.sin(theta), math.cos(theta)])
        outline = np.asarray(self.center) + np.cos(angles)[:, None] * major * along
        return np.asarray(outline + np.sin(angles)[:, None] * minor * across, dtype=np.float64)


class UnboundedGeometry(Frozen):
    """The whole plane: too few calibration scores for this epsilon (t = 0) to bound the set."""

    @property
    def area(self) -> float:
        return math.inf

    def contains(self, points: ArrayLike) -> NDArray[np.bool_]:
        """Always true: for an (N, 2) array, N times True."""
        offsets = _offsets(points, (0.0, 0.0))
        return np.ones(offsets.shape[:-1], dtype=bool)

    def boundary(self, n: int = 64) -> NDArray[np.float64]:
        """No boundary: an empty (0, 2) array (there is nothing to draw)."""
        _angles(n)
        return np.empty((0, 2))
