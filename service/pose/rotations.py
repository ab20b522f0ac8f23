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
    """B (3, 3, 4, 4) with R(q)_jk = q^T B_jk q for a unit quaternion q = (w, x, y, z), by polarising
    R(q) = (w^2 - |v|^2) I + 2 v v^T + 2 w [v]_x, v = (x, y, z)."""

    def rotation(q: np.ndarray) -> np.ndarray:
        w, v = q[0], q[1:]
        return (w * w - v @ v) * np.eye(3) + 2 * np.outer(v, v) + 2 * w * np.cross(np.eye(3), v)

    unit = np.eye(4)
    polarised = [
        [(rotation(unit[a] + unit[b]) - rotation(unit[a] - unit[b])) / 4 for b in range(4)] for a in range(4)
    ]
    return np.array(polarised).transpose(2, 3, 0, 1)


QUATERNION_BASIS = _quaternion_basis()
