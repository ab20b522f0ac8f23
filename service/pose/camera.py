"""The camera matrix of a pose request: what makes a K usable for projection.

K maps camera coordinates to the response's image coordinates (the coordinates of the
sets and of COCO labels): ``y = (K p)[:2] / (K p)[2]``. OpenCV's PnP reads only fx, fy,
cx and cy, so a skewed K would be served wrongly: it is refused rather than ignored.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def camera_matrix_problems(matrix: Sequence[Sequence[float]]) -> list[str]:
    """What is wrong with a pinhole camera matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (empty: fine)."""
    rows = [list(row) for row in matrix]
    if len(rows) != 3 or any(len(row) != 3 for row in rows):
        return ["must be 3 rows of 3 numbers: [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]"]
    problems = [
        f"[{r}][{c}] is {value!r}; every entry must be a finite number"
        for r, row in enumerate(rows)
        for c, value in enumerate(row)
        if not math.isfinite(value)
    ]
    if problems:
        return problems
    if rows[0][0] <= 0 or rows[1][1] <= 0:
        problems.append(f"fx = K[0][0] = {rows[0][0]:g} and fy = K[1][1] = {rows[1][1]:g} must both be > 0")
    if rows[0][1] != 0 or rows[1][0] != 0:
        problems.append("K[0][1] (skew) and K[1][0] must be 0: OpenCV's PnP ignores skew")
    if rows[2] != [0, 0, 1]:
        problems.append(f"the last row must be [0, 0, 1], not {rows[2]}")
    return problems


def as_camera_matrix(matrix: Sequence[Sequence[float]]) -> np.ndarray:
    """K as a float64 (3, 3) array, refusing a malformed one with ``ValueError`` (one line per problem)."""
    problems = camera_matrix_problems(matrix)
    if problems:
        raise ValueError("; ".join(problems))
    return np.asarray(matrix, dtype=np.float64)


def ray_frame(translation: np.ndarray) -> np.ndarray:
    """Orthonormal rows, the first along the line of sight to ``translation`` (the depth error
    dominates there), the others across it."""
    ray = translation / (np.linalg.norm(translation) or 1.0)
    helper = np.eye(3)[int(np.argmin(np.abs(ray)))]
    second = np.cross(ray, helper)
    second /= np.linalg.norm(second)
    return np.vstack([ray, second, np.cross(ray, second)])
