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
from functools import cached_property

import numpy as np

from .rotations import left_product, to_quaternion


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
_LARGEST_GIBBS_ANGLE = math.radians(160.0)  # beyond, one box of Gibbs vectors would be too large


def _sides() -> tuple[np.ndarray, np.ndarray]:
    """Pairs (i, j) of a wedge's forms (Wedge.forms) whose products are the sides: q_j's own two
    bounds, which cut the wedge out exactly, then a bound of q_j with a bound of q_k (RLT products):
    valid for every rotation of the wedge, they tighten its relaxation, so that a search proves
    wedges empty sooner (a fifth fewer programs on rendered sequences)."""
    own = [(1 + 2 * k, 2 + 2 * k) for k in range(3)]
    cross = [(i, j) for i in range(1, 7) for j in range(i + 1, 7) if (i - 1) // 2 != (j - 1) // 2]
    first, second = zip(*own, *cross, strict=True)
    return np.array(first), np.array(second)


SIDES = _sides()
_OTHERS = [[j for j in range(4) if j != face] for face in range(4)]  # per face, u's components
_LOWER_ROWS, _UPPER_ROWS = [1, 3, 5], [2, 4, 6]  # of Wedge.forms: u_k's lower and upper bound


@dataclass(frozen=True)
class Wedge:
    """The rotations R_hat R(q) whose quaternion q = (q_0, .., q_3) (up to sign) has its largest
    component in magnitude at ``face`` and u = (q_j / q_face)_{j != face} in the box [low, high]:
    the four faces of the 4-cube around R_hat, as ``Cell`` around the identity. Face 0 holds the
    rotations turned at most 90 degrees about every axis; there u is the Gibbs vector
    tan(angle / 2) * axis.

    A wedge lies in its circumscribed cap, and its box is cut out exactly by three quadratic
    constraints, linear in the moment matrix Q = q q^T: low_j <= q_j / q_face <= high_j <=>
    (q_j - low_j q_face)(q_j - high_j q_face) <= 0 (q_face = 0 would force q = 0); the products of
    the bounds of two different components (``SIDES``) are valid too and tighten the relaxation."""

    face: int
    low: tuple[float, float, float]
    high: tuple[float, float, float]

    @staticmethod
    def around(radius: float) -> list[Wedge]:
        """Wedges holding every rotation within ``radius`` of R_hat: one box of Gibbs vectors
        |g| <= tan(radius / 2), off-centre (``_OFFSET``: centred, the estimate would be a corner of
        every cell near it, and all of them would hold poses of PURSE and need splitting); the four
        faces of the 4-cube when ``radius`` is near pi."""
        if radius > _LARGEST_GIBBS_ANGLE:
            return [Wedge(face, (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)) for face in range(4)]
        reach = math.tan(radius / 2)
        centre, half = np.array(_OFFSET) * reach, reach * (1 + max(_OFFSET))
        return [Wedge(0, tuple((centre - half).tolist()), tuple((centre + half).tolist()))]

    def _quaternion(self, u: np.ndarray) -> np.ndarray:
        q = np.insert(np.asarray(u, dtype=np.float64), self.face, 1.0)
        return q / np.linalg.norm(q)

    def _corners(self) -> list[np.ndarray]:
        low, high = np.array(self.low), np.array(self.high)
        return [np.where(bits, high, low) for bits in itertools.product([0, 1], repeat=3)]

    def cap(self, estimate: np.ndarray) -> tuple[np.ndarray, float]:
        """(q_0, cos^2(phi)) with (q_0^T q)^2 >= cos^2(phi) over the wedge (as ``Cell.cap``)."""
        centre = self._quaternion((np.array(self.low) + np.array(self.high)) / 2)
        cosine = min(abs(float(centre @ self._quaternion(corner))) for corner in self._corners())
        return left_product(to_quaternion(estimate)) @ centre, cosine**2

    def forms(self, anchor: np.ndarray) -> np.ndarray:
        """(7, 4): linear forms g with g^T q >= 0 on the wedge, in absolute quaternion coordinates
        (``anchor`` = left_product(to_quaternion(R_hat))): with q_face >= 0 (q and -q are one
        rotation), q_face, then q_j - low_j q_face and high_j q_face - q_j per other component."""
        relative = np.zeros((7, 4))
        others = _OTHERS[self.face]
        relative[0, self.face] = 1.0
        relative[_LOWER_ROWS, others] = 1.0
        relative[_UPPER_ROWS, others] = -1.0
        relative[_LOWER_ROWS, self.face] = np.negative(self.low)
        relative[_UPPER_ROWS, self.face] = self.high
        return relative @ anchor.T

    def sides(self, estimate: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per side, (a, b) in absolute quaternion coordinates: a^T q q^T b <= 0 on the wedge."""
        forms = self.forms(left_product(to_quaternion(estimate)))
        return [(-forms[i], forms[j]) for i, j in zip(*SIDES, strict=True)]

    @cached_property
    def _angle_cosines(self) -> tuple[float, float]:
        """The least and largest |cos(angle / 2)| = |q_0| / |q| over the wedge's rotations (in plain
        floats: a search computes this for every wedge it makes)."""
        bounds = list(zip(self.low, self.high, strict=True))
        near = [0.0 if low <= 0 <= high else min(abs(low), abs(high)) for low, high in bounds]
        far = [max(abs(low), abs(high)) for low, high in bounds]
        if self.face == 0:  # q_0 = 1: cos = 1 / sqrt(1 + |u|^2)
            return 1 / math.sqrt(1 + _squared(far)), 1 / math.sqrt(1 + _squared(near))
        # q_0 = u_0 q_face: cos = |u_0| / sqrt(1 + |u|^2), increasing in |u_0|, decreasing in the rest
        rest_near, rest_far = _squared(near[1:]), _squared(far[1:])
        least = near[0] / math.sqrt(1 + near[0] ** 2 + rest_far)
        return least, far[0] / math.sqrt(1 + far[0] ** 2 + rest_near)

    def farthest_angle(self) -> float:
        """An upper bound on the angle (radians) from R_hat to the wedge's rotations."""
        return 2.0 * math.acos(min(1.0, self._angle_cosines[0]))

    def nearest_angle(self) -> float:
        """A lower bound on the angle (radians) from R_hat to the wedge's rotations."""
        return 2.0 * math.acos(min(1.0, self._angle_cosines[1]))

    def split(self, radius: float) -> list[Wedge]:
        """The eight half-size boxes, less those holding no rotation within ``radius`` of R_hat."""
        halves = [
            ((low, (low + high) / 2), ((low + high) / 2, high))
            for low, high in zip(self.low, self.high, strict=True)
        ]
        children = []
        for parts in itertools.product(*halves):
            child = Wedge(self.face, tuple(p[0] for p in parts), tuple(p[1] for p in parts))
            if child.nearest_angle() <= radius:
                children.append(child)
        return children


def _squared(values: list[float]) -> float:
    return sum(value * value for value in values)
