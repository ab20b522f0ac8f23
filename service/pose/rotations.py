"""Rotation helpers: geodesic distance on SO(3) and the quaternion lift of a rotation."""

from __future__ import annotations

import math

import cv2
import numpy as np


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Geodesic distance between two rotations, in degrees: arccos((tr(A^T B) - 1) / 2)."""
    cosine = (float(np.trace(a.T @ b)) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, cosine))))


def from_rotation_vector(rvec: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))[0]


def to_rotation_vector(rotation: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(rotation, dtype=np.float64))[0].reshape(3)


def to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """A unit quaternion (w, x, y, z) of the rotation, in the convention of QUATERNION_BASIS."""
    vector = to_rotation_vector(rotation)
    angle = float(np.linalg.norm(vector))
    if angle == 0.0:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * vector / angle])


def left_product(q: np.ndarray) -> np.ndarray:
    """L(q) with q (x) p = L(q) p, the Hamilton product of quaternions (w, x, y, z): the quaternion of
    R(q) R(p)."""
    w, x, y, z = q
    return np.array([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]])


def _quaternion_basis() -> np.ndarray:
    """B (3, 3, 4, 4) with R(q)_jk = q^T B_jk q for a unit quaternion q = (w, x, y, z)."""
    basis = np.zeros((3, 3, 4, 4))
    w, x, y, z = range(4)
    terms = {  # R(q) entries as sums of coefficient * q_a * q_b
        (0, 0): [(1, w, w), (1, x, x), (-1, y, y), (-1, z, z)],
        (0, 1): [(2, x, y), (-2, w, z)],
        (0, 2): [(2, x, z), (2, w, y)],
        (1, 0): [(2, x, y), (2, w, z)],
        (1, 1): [(1, w, w), (-1, x, x), (1, y, y), (-1, z, z)],
        (1, 2): [(2, y, z), (-2, w, x)],
        (2, 0): [(2, x, z), (-2, w, y)],
        (2, 1): [(2, y, z), (2, w, x)],
        (2, 2): [(1, w, w), (-1, x, x), (-1, y, y), (1, z, z)],
    }
    for (j, k), entries in terms.items():
        for coefficient, a, b in entries:
            basis[j, k, a, b] += coefficient / 2
            basis[j, k, b, a] += coefficient / 2
    return basis


QUATERNION_BASIS = _quaternion_basis()
