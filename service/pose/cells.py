"""Cells of rotation space for the branch-and-bound of the outer bound (relaxation.py).

``Cube``: the rotations R_hat exp([w]) around an estimate R_hat for w in a cube (centre w_0, half
side h), the cells of the best-first search. The geodesic angle between exp([u]) and exp([v]) is at
most |u - v| (Hartley & Kahl, IJCV 2009), so a cube lies in the cap of angle sqrt(3) h around
R_hat exp([w_0]), and its rotations are at most min(pi, max |w|) from R_hat.

``Cell`` (the older, rounds-based branch-and-bound):

Every rotation has a unit quaternion q with a largest component q_k > 0 (q and -q are the same
rotation), so the four "faces" {q : q_k >= |q_j|} of the 4-cube, projected onto the unit sphere,
cover SO(3). A cell is such a face restricted to a box of u = (q_j / q_k)_{j != k}; splitting a
box in 8 splits the cell. Each cell lies in a cap {q : |q_0^T q| >= cos(phi)} around the unit
quaternion q_0 of its box centre: the angle to q_0 is largest at a box corner (the cosine to q_0
is quasi-concave on the cone over the box), so phi is the largest corner angle. In the lifted
relaxation the cap is the linear constraint q_0^T Q q_0 >= cos^2(phi), which keeps Q, hence
R = A(Q), near rank one: the convex hull of SO(3) alone also holds the shrunk rotations
alpha R, which project like R when t shrinks with them.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from .rotations import from_rotation_vector, to_quaternion


@dataclass(frozen=True)
class Cell:
    face: int  # k: the quaternion component that is largest in magnitude
    low: tuple[float, float, float]  # the box of u = (q_j / q_k), j != k
    high: tuple[float, float, float]

    def _quaternion(self, u: np.ndarray) -> np.ndarray:
        q = np.insert(np.asarray(u, dtype=np.float64), self.face, 1.0)
        return q / np.linalg.norm(q)

    def cap(self) -> tuple[np.ndarray, float]:
        """(q_0, cos^2(phi)): every quaternion of the cell has (q_0^T q)^2 >= cos^2(phi)."""
        low, high = np.array(self.low), np.array(self.high)
        centre = self._quaternion((low + high) / 2)
        bits = itertools.product([0, 1], repeat=3)
        corners = [self._quaternion(np.where(corner, high, low)) for corner in bits]
        return centre, min(float(centre @ corner) ** 2 for corner in corners)

    def split(self) -> list[Cell]:
        low, high = np.array(self.low), np.array(self.high)
        middle = (low + high) / 2
        children = []
        for bits in itertools.product([0, 1], repeat=3):
            child_low = np.where(bits, middle, low)
            child_high = np.where(bits, high, middle)
            children.append(Cell(self.face, tuple(child_low.tolist()), tuple(child_high.tolist())))
        return children


def root_cells() -> list[Cell]:
    """Four cells that cover SO(3)."""
    return [Cell(face, (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)) for face in range(4)]


# The first cube is off-centre: centred at the estimate, every cube of the binary grid near it would
# have the estimate on a corner, hence hold poses of PURSE, and would all have to be split.
_OFFSET = (0.23, 0.13, 0.07)


@dataclass(frozen=True)
class Cube:
    """The rotations R_hat exp([w]) for w in the cube |w - centre|_inf <= half."""

    centre: tuple[float, float, float]
    half: float

    @staticmethod
    def around(radius: float) -> Cube:
        """The cube holding the ball |w| <= radius: every rotation within ``radius`` of R_hat."""
        offset = np.array(_OFFSET) * radius
        return Cube(tuple(offset.tolist()), radius * (1 + max(_OFFSET)))

    def cap(self, estimate: np.ndarray) -> tuple[np.ndarray, float] | None:
        """(q_0, cos^2(phi)) with (q_0^T q)^2 >= cos^2(phi) over the cube (None: no constraint)."""
        half_angle = math.sqrt(3.0) * self.half / 2  # a quaternion turns half the rotation angle
        if half_angle >= math.pi / 2:
            return None
        centre = to_quaternion(estimate @ from_rotation_vector(np.array(self.centre)))
        return centre, math.cos(half_angle) ** 2

    def farthest_angle(self) -> float:
        """An upper bound on the angle (radians) from R_hat to the cube's rotations."""
        return min(math.pi, float(np.linalg.norm(np.abs(self.centre) + self.half)))

    def split(self, radius: float) -> list[Cube]:
        """The eight half-size cubes, less those entirely outside the ball |w| <= radius."""
        half = self.half / 2
        children = []
        for signs in itertools.product((-1.0, 1.0), repeat=3):
            centre = np.array(self.centre) + half * np.array(signs)
            if np.linalg.norm(np.maximum(np.abs(centre) - half, 0.0)) <= radius:
                children.append(Cube(tuple(centre.tolist()), half))
        return children
