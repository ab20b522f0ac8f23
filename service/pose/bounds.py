"""The inner bound on the pose error (docs/pose.md, "Inner"): poses found inside PURSE, by PnP on
draws inside the sets (Yang & Pavone, CVPR 2023, sec. 4.2) and by a boundary search (after CLOSURE,
Gao, Tang, Qi & Yang, 2024) that pushes the estimate by SLSQP along and against the line of sight
and away in rotation. Their largest distances from the estimate bound the worst-case error from
below; the relaxation (relaxation.py) bounds it from above.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from .camera import ray_frame
from .membership import Pose, membership, poses_inside
from .rotations import from_rotation_vector, rotation_angle_deg


@dataclass(frozen=True)
class InnerBound:
    """Largest distances from the estimate to the poses found in PURSE (a lower bound on the worst case)."""

    rotation_deg: float
    translation: float
    poses_found: int
    poses_tried: int
    boundary_poses: int = 0  # how many of the poses found came from the boundary search


@dataclass(frozen=True)
class SampledPoses:
    poses: list[Pose]
    tried: int
    boundary: int = 0


def sample_points_in_sets(
    centers: np.ndarray, shapes: np.ndarray, rng: np.random.Generator, count: int = 1
) -> np.ndarray:
    """(count, N, 2): one point per set and draw, uniform over the ball or ellipse
    {y : (y - c)^T L (y - c) <= 1}."""
    values, vectors = np.linalg.eigh(shapes)
    half_axes = 1.0 / np.sqrt(values)  # per principal direction
    draws = rng.random((count, 2, len(centers)))  # per draw: the angles, then the radii
    angle, radius = 2.0 * np.pi * draws[:, 0], np.sqrt(draws[:, 1])
    unit_disc = np.stack([np.cos(angle), np.sin(angle)], axis=-1) * radius[..., None]
    return centers + np.einsum("nij,snj->sni", vectors, unit_disc * half_axes)


def sample_poses_in_set(
    start: Pose,
    camera: np.ndarray,
    keypoints_3d: np.ndarray,
    centers: np.ndarray,
    shapes: np.ndarray,
    count: int,
    seed: int = 0,
) -> SampledPoses:
    """PnP on ``count`` draws of keypoint positions inside the sets (every one bounded); the poses
    that land in PURSE."""
    if count == 0:
        return SampledPoses([], 0)
    points = sample_points_in_sets(centers, shapes, np.random.default_rng(seed), count)
    rotations, translations = _fitted_poses(start, camera, keypoints_3d.astype(np.float64), points)
    inside = poses_inside(rotations, translations, camera, keypoints_3d, centers, shapes)
    inside &= np.isfinite(translations).all(axis=1)
    found = [Pose(r, t) for r, t in zip(rotations[inside], translations[inside], strict=True)]
    return SampledPoses(found, count)


_GAUSS_NEWTON_STEPS = 8  # from the estimate to draws inside the sets: converged to rounding by then


def _fitted_poses(start: Pose, camera: np.ndarray, objects: np.ndarray, points: np.ndarray):
    """Least-squares PnP for every draw of ``points`` (S, N, 2) at once: Gauss-Newton from ``start``
    on the reprojection error, R <- exp([w]) R, one batch of 6x6 systems. Returns (S, 3, 3), (S, 3)."""
    count = len(points)
    rotations = np.repeat(start.rotation[None].astype(np.float64), count, axis=0)
    translations = np.repeat(start.translation[None].astype(np.float64), count, axis=0)
    focal, principal = np.array([camera[0, 0], camera[1, 1]]), camera[:2, 2]
    with np.errstate(all="ignore"):
        for _ in range(_GAUSS_NEWTON_STEPS):
            turned = objects @ rotations.transpose(0, 2, 1)  # (S, N, 3): R X
            camera_points = turned + translations[:, None]
            depth = camera_points[..., 2:3]
            residuals = focal * camera_points[..., :2] / depth + principal - points  # (S, N, 2)
            projection = np.zeros(camera_points.shape[:2] + (2, 3))  # d y / d p
            projection[..., 0, 0], projection[..., 1, 1] = focal[0] / depth[..., 0], focal[1] / depth[..., 0]
            projection[..., :, 2] = -focal * camera_points[..., :2] / depth**2
            turning = -_skew(turned)  # d p / d w = -[R X]_x
            jacobian = np.concatenate([projection @ turning, projection], axis=-1).reshape(count, -1, 6)
            normal = jacobian.transpose(0, 2, 1) @ jacobian
            gradient = jacobian.transpose(0, 2, 1) @ residuals.reshape(count, -1, 1)
            damping = 1e-9 * np.trace(normal, axis1=1, axis2=2)[:, None, None] * np.eye(6)
            try:
                step = -np.linalg.solve(normal + damping, gradient)[..., 0]
            except np.linalg.LinAlgError:  # a degenerate draw or camera: least squares still answers
                step = -(np.linalg.pinv(normal + damping) @ gradient)[..., 0]
            rotations = _exponential(step[:, :3]) @ rotations
            translations = translations + step[:, 3:]
    return rotations, translations


def _skew(vectors: np.ndarray) -> np.ndarray:
    """[v]_x for every vector of (..., 3)."""
    x, y, z, zero = *np.moveaxis(vectors, -1, 0), np.zeros(vectors.shape[:-1])
    return np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(vectors.shape[:-1] + (3, 3))


def _exponential(vectors: np.ndarray) -> np.ndarray:
    """Rodrigues' formula for every rotation vector of (S, 3)."""
    angle = np.linalg.norm(vectors, axis=1)[:, None, None]
    cross = _skew(vectors)
    small = angle < 1e-12
    safe = np.where(small, 1.0, angle)
    sine = np.where(small, 1.0, np.sin(safe) / safe)
    cosine = np.where(small, 0.5, (1 - np.cos(safe)) / safe**2)
    return np.eye(3) + sine * cross + cosine * (cross @ cross)


def boundary_search_available() -> bool:
    """Whether SciPy (the `pose` extra) is installed: without it the inner bound is sampling's alone."""
    try:
        import scipy.optimize  # noqa: F401
    except ImportError:
        return False
    return True


_ROTATION_STARTS = 0.05  # radians: the rotation search starts this far from the estimate
#: SLSQP runs converged this far: stopped at 1e-6, their poses moved in the 8th digit with the
#: BLAS library's thread count, so the same request got other inner bounds on other machines
BOUNDARY_FTOL = 1e-9
#: SLSQP stops within its tolerance of the boundary it pushes against, a hair inside or out as the
#: last bits fall (and the way back to the estimate may leave PURSE): it is asked to keep this inside
_MARGIN = 1e-6
#: a turn of at most pi about each axis, a translation within 90 % of the distance: without bounds a
#: run could step to turns of 1e7 radians, and diverge or not with the BLAS library's thread count
_BOUNDS = [(-np.pi, np.pi)] * 3 + [(-9.0, 9.0)] * 3
_SLSQP = {"method": "SLSQP", "options": {"maxiter": 60, "ftol": BOUNDARY_FTOL}}


def boundary_poses(
    estimate: Pose, camera: np.ndarray, keypoints_3d: np.ndarray, centers: np.ndarray, shapes: np.ndarray
) -> list[Pose]:
    """Poses of PURSE pushed to its boundary (every set bounded): the farthest along and against the
    line of sight, and in rotation from four small turns about the two axes across it. The variable is
    x = (w, u): the rotation exp([w]) R_hat, and t = t_hat + step u with step a tenth of the distance:
    SLSQP sees radians and tenths of the depth on one scale. The turn w is taken from the estimate, so
    that it stays small, away from the rotation vector's singularity at pi (an estimate's own may be
    near it)."""
    from scipy.optimize import minimize  # the `pose` extra (Clarabel needs SciPy): not at start-up

    objects = keypoints_3d.astype(np.float64) @ estimate.rotation.T  # R_hat X: the estimate's turn
    step = 0.1 * (float(np.linalg.norm(estimate.translation)) or 1.0)
    scaled = np.array([1.0, 1.0, 1.0, step, step, step])  # d (w, t) / d x
    moved = np.tile([0.0, 0.0, step], (len(objects), 1))  # d z_i / d u

    @lru_cache(maxsize=1)  # SLSQP asks for the constraints, then their Jacobian, at one point
    def feasible(key: bytes):  # per keypoint, 1 - (y_i - c_i)^T L_i (y_i - c_i) >= 0 and z_i > 0
        x = np.frombuffer(key)
        translation = estimate.translation + step * x[3:]
        projected, jacobian = cv2.projectPoints(objects, x[:3], translation, camera, None)
        offsets = projected.reshape(-1, 2) - centers
        slopes = -2 * np.einsum("ni,nij,njk->nk", offsets, shapes, jacobian[:, :6].reshape(-1, 2, 6) * scaled)
        slack = 1.0 - _MARGIN - np.einsum("ni,nij,nj->n", offsets, shapes, offsets)
        rotation, turning = cv2.Rodrigues(x[:3])  # Rodrigues' d vec(R) / d w, row-major
        depth = (objects @ rotation.T + translation)[:, 2]
        gradients = np.vstack([slopes, np.hstack([objects @ turning[:, 6:9].T, moved])])
        return np.concatenate([slack, depth]), gradients

    def turn(x):  # tr(R_hat^T R) = tr(exp([w])): smallest at the largest angle
        rotation, jacobian = cv2.Rodrigues(x[:3])
        return float(np.trace(rotation)), np.concatenate([jacobian @ np.eye(3).reshape(9), np.zeros(3)])

    constraint = {"type": "ineq", "fun": lambda x: feasible(x.tobytes())[0]}
    constraint["jac"] = lambda x: feasible(x.tobytes())[1]
    sight, *across = ray_frame(estimate.translation)
    start = np.zeros(6)
    runs = [
        (lambda x, a=sign * sight: (-float(a @ x[3:]), np.concatenate([np.zeros(3), -a])), start)
        for sign in (1.0, -1.0)
    ]
    for axis, sign in itertools.product(across, (1.0, -1.0)):
        runs.append((turn, np.concatenate([sign * _ROTATION_STARTS * axis, np.zeros(3)])))
    poses, origin = [], np.concatenate([start[:3], estimate.translation])
    for objective, x0 in runs:
        try:
            with np.errstate(all="ignore"):
                result = minimize(objective, x0, jac=True, constraints=[constraint], bounds=_BOUNDS, **_SLSQP)
        except (cv2.error, ValueError):  # a run wandering off to poses OpenCV cannot project
            continue
        end = np.concatenate([result.x[:3], estimate.translation + step * result.x[3:]])
        pose = _inside_towards(origin, end, estimate.rotation, camera, keypoints_3d, centers, shapes)
        if pose is not None:
            poses.append(pose)
    return poses


_BISECTION_STEPS = 30  # halvings of the segment towards the estimate
_TOWARDS_HIGH = 2.0 ** -np.arange(1, _BISECTION_STEPS + 1)  # the middles of the halvings left, as fractions


def _inside_towards(start, end, base: np.ndarray, *scene) -> Pose | None:
    """The pose at ``end`` (turn w of ``base``, translation) if it is in PURSE, else the last one in
    PURSE on the segment from ``start`` (by bisection; None if ``end`` is not finite)."""
    if not np.isfinite(end).all():
        return None

    def pose_at(fraction: float) -> Pose:
        x = start + fraction * (end - start)
        return Pose(from_rotation_vector(x[:3]) @ base, x[3:].copy())

    if membership(pose_at(1.0), *scene).inside:
        return pose_at(1.0)
    # SLSQP ends a hair outside PURSE, so nearly every middle of the bisection lands inside: one batch
    # checks the middles (low + high) / 2 that path would visit (exact dyadic fractions), and the
    # bisection goes on from the first that does not
    low, high, steps = 0.0, 1.0, _BISECTION_STEPS
    while steps:
        middles = high - (high - low) * _TOWARDS_HIGH[:steps]
        x = start + middles[:, None] * (end - start)
        rotations = np.array([from_rotation_vector(v) @ base for v in x[:, :3]])  # pose_at's, exactly
        inside = poses_inside(rotations, x[:, 3:], *scene)
        kept = steps if inside.all() else int(inside.argmin())  # the middles inside before one outside
        if kept:
            low = float(middles[kept - 1])
        if kept < steps:
            high = float(middles[kept])
        steps -= min(kept + 1, steps)
    pose = pose_at(low)
    return pose if membership(pose, *scene).inside else None


def inner_bound(estimate: Pose, sampled: SampledPoses) -> InnerBound:
    """The largest rotation and translation distances from ``estimate`` to the sampled poses."""
    rotation = max((rotation_angle_deg(estimate.rotation, p.rotation) for p in sampled.poses), default=0.0)
    translation = max(
        (float(np.linalg.norm(p.translation - estimate.translation)) for p in sampled.poses), default=0.0
    )
    found = len(sampled.poses) - sampled.boundary
    return InnerBound(rotation, translation, found, sampled.tried, sampled.boundary)
