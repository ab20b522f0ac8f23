"""Pinhole camera in the OpenCV convention and its pybullet (OpenGL) matrices.

Image coordinates are continuous with the origin at the top-left corner of the
top-left pixel, so the principal point of a centred camera is ``(W / 2, H / 2)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Camera:
    width: int
    height: int
    focal: float  # pixels, fx = fy
    rotation: np.ndarray  # world -> camera (OpenCV: x right, y down, z forward)
    translation: np.ndarray  # metres
    near: float = 0.05
    far: float = 5.0

    @property
    def intrinsics(self) -> np.ndarray:
        return np.array([[self.focal, 0, self.width / 2], [0, self.focal, self.height / 2], [0, 0, 1.0]])

    def to_camera(self, points_world: np.ndarray) -> np.ndarray:
        return points_world @ self.rotation.T + self.translation

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """``(N, 3)`` camera-frame points -> ``(N, 2)`` continuous pixel coordinates."""
        k = self.intrinsics
        z = points_cam[:, 2:3]
        return points_cam[:, :2] / z * np.array([k[0, 0], k[1, 1]]) + k[:2, 2]

    def view_matrix(self) -> list[float]:
        """pybullet view matrix (column-major, OpenGL camera looking down -z)."""
        flip = np.diag([1.0, -1.0, -1.0])
        view = np.eye(4)
        view[:3, :3] = flip @ self.rotation
        view[:3, 3] = flip @ self.translation
        return view.T.reshape(-1).tolist()

    def projection_matrix(self) -> list[float]:
        """pybullet projection matrix matching the intrinsics (symmetric frustum)."""
        n, f = self.near, self.far
        proj = np.zeros((4, 4))
        proj[0, 0] = 2 * self.focal / self.width
        proj[1, 1] = 2 * self.focal / self.height
        proj[2, 2] = -(f + n) / (f - n)
        proj[2, 3] = -2 * f * n / (f - n)
        proj[3, 2] = -1.0
        return proj.T.reshape(-1).tolist()

    def metric_depth(self, depth_buffer: np.ndarray) -> np.ndarray:
        """OpenGL depth buffer in [0, 1] -> camera-frame z in metres."""
        n, f = self.near, self.far
        return f * n / (f - (f - n) * depth_buffer)


def look_at(eye: np.ndarray, target: np.ndarray, roll: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """World->camera rotation and translation for a camera at ``eye`` looking at ``target``."""
    forward = target - eye
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
    if np.linalg.norm(right) < 1e-6:
        right = np.array([1.0, 0.0, 0.0])
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])  # rows: camera axes in world
    c, s = np.cos(roll), np.sin(roll)
    rotation = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]) @ rotation
    return rotation, -rotation @ eye
