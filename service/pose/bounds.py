"""The inner (sampled) bound on the pose error: poses found inside PURSE by sampling.

As in the RANSAC-style search of Yang & Pavone (CVPR 2023, sec. 4.2): draw one position inside
every keypoint's set (uniform over the ball or ellipse), solve PnP on them from the estimate,
keep the poses that are in PURSE. The largest rotation (geodesic) and translation distances from
the estimate to the kept poses are a lower bound on the worst-case error over PURSE: the true
pose may be any of them. It is not an upper bound; that is the relaxation's job (relaxation.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .membership import Pose, membership
from .rotations import from_rotation_vector, rotation_angle_deg, to_rotation_vector


@dataclass(frozen=True)
class InnerBound:
    """Largest distances from the estimate to the poses found in PURSE (a lower bound on the worst case)."""

    rotation_deg: float
    translation: float
    poses_found: int
    poses_tried: int


@dataclass(frozen=True)
class SampledPoses:
    poses: list[Pose]
    tried: int


def sample_points_in_sets(centers: np.ndarray, shapes: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One point per set, uniform over the ball or ellipse {y : (y - c)^T L (y - c) <= 1}."""
    values, vectors = np.linalg.eigh(shapes)
    half_axes = 1.0 / np.sqrt(values)  # per principal direction
    angle = rng.uniform(0.0, 2.0 * np.pi, len(centers))
    radius = np.sqrt(rng.uniform(0.0, 1.0, len(centers)))
    unit_disc = np.stack([np.cos(angle), np.sin(angle)], axis=1) * radius[:, None]
    return centers + np.einsum("nij,nj->ni", vectors, unit_disc * half_axes)


def sample_poses_in_set(
    start: Pose,
    camera: np.ndarray,
    keypoints_3d: np.ndarray,
    centers: np.ndarray,
    shapes: np.ndarray,
    count: int,
    seed: int = 0,
) -> SampledPoses:
    """PnP on ``count`` draws of keypoint positions inside the sets; the poses that land in PURSE.

    Every set must be bounded (an unbounded set has no uniform draw).
    """
    rng = np.random.default_rng(seed)
    objects = keypoints_3d.astype(np.float64)
    rvec0, tvec0 = to_rotation_vector(start.rotation), start.translation.astype(np.float64)
    found = []
    for _ in range(count):
        points = sample_points_in_sets(centers, shapes, rng)
        try:
            ok, rvec, tvec = cv2.solvePnP(
                objects, points, camera, None, rvec0.copy(), tvec0.copy(), True, cv2.SOLVEPNP_ITERATIVE
            )
        except cv2.error:
            ok = False
        if not ok or not np.isfinite(tvec).all():
            continue
        pose = Pose(from_rotation_vector(rvec), tvec.reshape(3))
        if membership(pose, camera, keypoints_3d, centers, shapes).inside:
            found.append(pose)
    return SampledPoses(found, count)


def inner_bound(estimate: Pose, sampled: SampledPoses) -> InnerBound:
    """The largest rotation and translation distances from ``estimate`` to the sampled poses."""
    rotation = max((rotation_angle_deg(estimate.rotation, p.rotation) for p in sampled.poses), default=0.0)
    translation = max(
        (float(np.linalg.norm(p.translation - estimate.translation)) for p in sampled.poses), default=0.0
    )
    return InnerBound(rotation, translation, len(sampled.poses), sampled.tried)
