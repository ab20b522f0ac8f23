"""Wedges of rotation space for the search that tightens the outer bound (docs/pose.md, "The search").

A wedge is the rotations R_hat R(q) whose unit quaternion q (up to sign) has its largest component at
``face`` and u = (q_j / q_face)_{j != face} in a box (on face 0, u is the Gibbs vector tan(angle / 2)
* axis); the four faces cover SO(3). The box is cut out exactly by constraints linear in Q = q q^T,
(q_j - low_j q_face)(q_j - high_j q_face) <= 0.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

# The first box is off-centre: centred at the estimate, every box of the binary grid near it would
# have the estimate on a corner, hence hold poses of PURSE, and would all have to be split.
_OFFSET = (0.23, 0.13, 0.07)
_LARGEST_GIBBS_ANGLE = math.radians(160.0)  # beyond, one box of Gibbs vectors would be too large
# Pairs (i, j) of Wedge.forms whose products are the sides: each u_k's own two bounds (exact), then the
# RLT products of bounds of two components, valid too: a search proves wedges empty sooner (a fifth
# fewer programs on rendered sequences).
SIDES = tuple(
    np.array(side)
    for side in zip(
        *[(1 + 2 * k, 2 + 2 * k) for k in range(3)],
        *[(i, j) for i in range(1, 7) for j in range(i + 1, 7) if (i - 1) // 2 != (j - 1) // 2],
        strict=True,
    )
)
_OTHERS = [[j for j in range(4) if j != face] for face in range(4)]  # per face, u's components


@dataclass(frozen=True)
class Wedge:
    face: int  # the quaternion component largest in magnitude
    low: tuple[float, float, float]  # the box of u = (q_j / q_face), j != face
    high: tuple[float, float, float]

    @staticmethod
    def around(radius: float) -> list[Wedge]:
        """Wedges holding every rotation within ``radius`` of R_hat: one off-centre box of Gibbs
        vectors |g| <= tan(radius / 2), or the four faces (all of SO(3)) when ``radius`` is near pi."""
        if radius > _LARGEST_GIBBS_ANGLE:
            return [Wedge(face, (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)) for face in range(4)]
        reach = math.tan(radius / 2)
        centre, half = np.array(_OFFSET) * reach, reach * (1 + max(_OFFSET))
        return [Wedge(0, tuple((centre - half).tolist()), tuple((centre + half).tolist()))]

    def forms(self, anchor: np.ndarray) -> np.ndarray:
        """(7, 4): linear forms g >= 0 on the wedge's q in absolute coordinates (``anchor`` =
        left_product(to_quaternion(R_hat))): q_face, then q_j - low_j q_face and high_j q_face - q_j."""
        relative, others = np.zeros((7, 4)), _OTHERS[self.face]
        relative[0, self.face] = 1.0
        relative[[1, 3, 5], others], relative[[2, 4, 6], others] = 1.0, -1.0
        relative[[1, 3, 5], self.face], relative[[2, 4, 6], self.face] = np.negative(self.low), self.high
        return relative @ anchor.T

    @cached_property
    def _angle_cosines(self) -> tuple[float, float]:
        """The least and largest |cos(angle / 2)| = |q_0| / |q| over the wedge (plain floats: a search
        computes this for every wedge it makes)."""
        bounds = list(zip(self.low, self.high, strict=True))
        near = [0.0 if low <= 0 <= high else min(abs(low), abs(high)) for low, high in bounds]
        far = [max(abs(low), abs(high)) for low, high in bounds]
        if self.face == 0:  # q_0 = 1: cos = 1 / sqrt(1 + |u|^2)
            return 1 / math.sqrt(1 + _squared(far)), 1 / math.sqrt(1 + _squared(near))
        # q_0 = u_0 q_face: cos = |u_0| / sqrt(1 + |u|^2), increasing in |u_0|, decreasing in the rest
        least = near[0] / math.sqrt(1 + near[0] ** 2 + _squared(far[1:]))
        return least, far[0] / math.sqrt(1 + far[0] ** 2 + _squared(near[1:]))

    def farthest_angle(self) -> float:
        """An upper bound on the angle (radians) from R_hat to the wedge's rotations."""
        return 2.0 * math.acos(min(1.0, self._angle_cosines[0]))

    def nearest_angle(self) -> float:
        """A lower bound on the angle (radians) from R_hat to the wedge's rotations."""
        return 2.0 * math.acos(min(1.0, self._angle_cosines[1]))

    def split(self, radius: float) -> list[Wedge]:
        """The eight half-size boxes, less those holding no rotation within ``radius`` of R_hat."""
        middles = [(low + high) / 2 for low, high in zip(self.low, self.high, strict=True)]
        halves = [((lo, mid), (mid, hi)) for lo, mid, hi in zip(self.low, middles, self.high, strict=True)]
        children = (Wedge(self.face, *zip(*parts, strict=True)) for parts in itertools.product(*halves))
        return [child for child in children if child.nearest_angle() <= radius]


def _squared(values: list[float]) -> float:
    return sum(value * value for value in values)
