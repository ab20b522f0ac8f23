"""Whether a pose lies in PURSE, the pose uncertainty set of Yang & Pavone (CVPR 2023, eq. 7).

PURSE = {(R, t) in SE(3) : for every keypoint i, the projection y_i of R X_i + t is in front of
the camera and inside its prediction set (y_i - c_i)^T L_i (y_i - c_i) <= 1}. With object-scope
sets (all of an object's keypoints covered at once with probability >= 1 - epsilon) the true pose
is in PURSE with the same probability. A ball of radius r has L = I / r^2; an unbounded set
(t = 0) has L = 0 and constrains only the side of the camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Pose:
    """Model-to-camera rigid motion: p_camera = rotation @ p_model + translation."""

    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,), in the units of the model's 3D keypoints


@dataclass(frozen=True)
class Membership:
    """Per keypoint: in front of the camera, and the normalised distance to its set's centre."""

    in_front: np.ndarray  # (N,) bool
    violations: np.ndarray  # (N,) sqrt((y - c)^T L (y - c)); <= 1 inside the set, inf behind the camera

    @property
    def inside(self) -> bool:
        return bool(self.in_front.all() and (self.violations <= 1.0).all())

    @property
    def worst(self) -> float:
        return float(self.violations.max())


def camera_points(pose: Pose, keypoints_3d: np.ndarray) -> np.ndarray:
    """(N, 3) keypoints in camera coordinates."""
    return keypoints_3d @ pose.rotation.T + pose.translation


def project(points_camera: np.ndarray, camera: np.ndarray) -> np.ndarray:
    """(N, 2) image coordinates of camera-frame points (no distortion)."""
    homogeneous = points_camera @ camera.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return homogeneous[:, :2] / homogeneous[:, 2:3]


def set_violations(points: np.ndarray, centers: np.ndarray, shapes: np.ndarray) -> np.ndarray:
    """sqrt((y_i - c_i)^T L_i (y_i - c_i)) per row: <= 1 exactly when y_i is in set i."""
    offsets = points - centers
    quadratic = np.einsum("ni,nij,nj->n", offsets, shapes, offsets)
    return np.sqrt(np.maximum(quadratic, 0.0))


def membership(
    pose: Pose, camera: np.ndarray, keypoints_3d: np.ndarray, centers: np.ndarray, shapes: np.ndarray
) -> Membership:
    """Exact PURSE membership of ``pose``, keypoint by keypoint."""
    points = camera_points(pose, keypoints_3d)
    in_front = points[:, 2] > 0
    violations = set_violations(project(points, camera), centers, shapes)
    violations = np.where(in_front & np.isfinite(violations), violations, np.inf)
    return Membership(in_front=in_front, violations=violations)


#: a pose of a batch this close (relative) to a set's edge or to the camera plane is checked alone
_EDGE = 1e-9


def poses_inside(
    rotations: np.ndarray,
    translations: np.ndarray,
    camera: np.ndarray,
    keypoints_3d: np.ndarray,
    centers: np.ndarray,
    shapes: np.ndarray,
) -> np.ndarray:
    """``membership(...).inside`` for many poses at once ((P, 3, 3), (P, 3)), decided in one batch
    but for the poses within rounding of a set's edge or of the camera plane (the batch rounds
    otherwise than one pose alone), which are checked alone: every answer is ``membership``'s."""
    points = keypoints_3d @ rotations.transpose(0, 2, 1) + translations[:, None]  # (P, N, 3)
    with np.errstate(all="ignore"):
        homogeneous = points @ camera.T
        offsets = homogeneous[..., :2] / homogeneous[..., 2:3] - centers
        quadratic = np.einsum("pni,nij,pnj->pn", offsets, shapes, offsets)
        depth = points[..., 2]
        inside = ((depth > 0) & (quadratic <= 1.0)).all(axis=1)
        near_plane = np.abs(depth) <= _EDGE * np.abs(points).max(axis=(1, 2))[:, None]
        unsure = ((np.abs(quadratic - 1.0) <= _EDGE) | near_plane | ~np.isfinite(quadratic)).any(axis=1)
    for k in np.flatnonzero(unsure):
        pose = Pose(rotations[k], translations[k])
        inside[k] = membership(pose, camera, keypoints_3d, centers, shapes).inside
    return inside


def pose_in_set(
    rotation: np.ndarray,
    translation: np.ndarray,
    camera: np.ndarray,
    keypoints_3d: np.ndarray,
    centers: np.ndarray,
    shapes: np.ndarray,
) -> bool:
    """Whether (R, t) is in PURSE: every projected keypoint in front of the camera and in its set."""
    pose = Pose(np.asarray(rotation, dtype=np.float64), np.asarray(translation, dtype=np.float64))
    return membership(pose, camera, keypoints_3d, centers, shapes).inside
