"""A pose inside PURSE (docs/pose.md, "Moving the estimate inside"): PnP on the set centres, then, if
needed, the largest normalised violation minimised over the 6-dof pose by Lawson's iteratively
reweighted least squares (one damped Gauss-Newton step per reweighting), stopping at the first pose
inside every set: any pose in PURSE is as good an estimate as another (Yang & Pavone, CVPR 2023).
"""

from __future__ import annotations

import cv2
import numpy as np

from .membership import Pose, membership
from .rotations import from_rotation_vector, to_rotation_vector

MIN_POINTS = 4  # EPnP's minimum
_DAMPING = 1e-6
_INSIDE_MARGIN = 1e-6  # aim a little inside, so that membership survives rounding


def pnp_on_centres(camera: np.ndarray, keypoints_3d: np.ndarray, centers: np.ndarray) -> Pose | None:
    """EPnP on the set centres, refined by Levenberg-Marquardt on the reprojection error."""
    if len(keypoints_3d) < MIN_POINTS:
        return None
    objects, images = keypoints_3d.astype(np.float64), centers.astype(np.float64)
    try:
        found, rvec, tvec = cv2.solvePnP(objects, images, camera, None, flags=cv2.SOLVEPNP_EPNP)
        if not found:
            return None
        rvec, tvec = cv2.solvePnPRefineLM(objects, images, camera, None, rvec, tvec)
    except cv2.error:  # degenerate input (e.g. an extreme camera matrix): no PnP solution
        return None
    if not (np.isfinite(rvec).all() and np.isfinite(tvec).all()):
        return None
    return Pose(from_rotation_vector(rvec), tvec.reshape(3))


def whitening(shapes: np.ndarray) -> np.ndarray:
    """W_i with W_i^T W_i = L_i (symmetric square roots), so that ||W_i d|| = sqrt(d^T L_i d)."""
    values, vectors = np.linalg.eigh(shapes)
    roots = np.sqrt(np.maximum(values, 0.0))
    return np.einsum("nij,nj,nkj->nik", vectors, roots, vectors)


def refine_into_set(
    start: Pose,
    camera: np.ndarray,
    keypoints_3d: np.ndarray,
    centers: np.ndarray,
    shapes: np.ndarray,
    iterations: int = 60,
) -> Pose | None:
    """A pose in PURSE near ``start`` (minimax of the normalised violations), or None."""
    whiten = whitening(shapes)
    rvec, tvec = to_rotation_vector(start.rotation), start.translation.astype(np.float64).copy()
    weights = np.full(len(centers), 1.0 / len(centers))
    objects = keypoints_3d.astype(np.float64)
    for _ in range(iterations):
        pose = Pose(from_rotation_vector(rvec), tvec.copy())
        check = membership(pose, camera, keypoints_3d, centers, shapes)
        if not check.in_front.all():
            return None
        if check.worst <= 1.0 - _INSIDE_MARGIN:
            return pose
        try:
            projected, jacobian = cv2.projectPoints(objects, rvec, tvec, camera, None)
            residuals = np.einsum("nij,nj->ni", whiten, projected.reshape(-1, 2) - centers)
            jacobians = np.einsum("nij,njk->nik", whiten, jacobian[:, :6].reshape(-1, 2, 6))
            weights = weights * np.maximum(np.linalg.norm(residuals, axis=1), 1e-12)  # Lawson
            weights /= weights.sum()
            hessian = np.einsum("n,nij,nik->jk", weights, jacobians, jacobians)
            gradient = np.einsum("n,nij,ni->j", weights, jacobians, residuals)
            step = np.linalg.solve(hessian + _DAMPING * np.trace(hessian) * np.eye(6), -gradient)
        except (cv2.error, np.linalg.LinAlgError):
            return None
        if not np.isfinite(step).all():
            return None
        rvec, tvec = rvec + step[:3], tvec + step[3:]
    return None
