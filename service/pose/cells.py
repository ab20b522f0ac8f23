"""Cells of rotation space for the branch-and-bound of the outer bound (relaxation.py).

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
from dataclasses import dataclass

import numpy as np


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
