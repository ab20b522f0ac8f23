"""Pose requests in, pose answers out: the edge between the API's schemas and service.pose."""

from __future__ import annotations

import math

import numpy as np

from service.api.schemas import (
    OuterBoundOut,
    PoseCheckOut,
    PoseOut,
    PredictParameters,
    SampledBoundOut,
)
from service.detector.manifest import Manifest
from service.pose import (
    Pose,
    PoseOptions,
    PoseSets,
    as_camera_matrix,
    check_pose_request,
)


def pose_options(parameters: PredictParameters, manifest: Manifest) -> PoseOptions | None:
    """The request's pose options, refused (422) when the sets cannot answer them; None: not asked."""
    request = parameters.pose
    if request is None:
        return None
    checks: dict[int, list[Pose]] = {}
    for check in request.check:
        pose = Pose(np.array(check.rotation, dtype=np.float64), np.array(check.translation, dtype=np.float64))
        checks.setdefault(check.instance, []).append(pose)
    camera = as_camera_matrix(request.K)
    options = PoseOptions(camera, request.samples, request.outer_bound, request.outer_splits, checks)
    objects = [instance.object for instance in parameters.instances]
    check_pose_request(manifest, objects, parameters.coverage, options)
    return options


def _matrix(array: np.ndarray) -> tuple:
    return tuple(tuple(float(v) for v in row) for row in array)


def _vector(array: np.ndarray) -> tuple:
    return tuple(float(v) for v in array)


def _finite_or_none(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def pose_out(answer: PoseSets) -> PoseOut:
    estimate, inner, outer = answer.estimate, answer.inner, answer.outer
    return PoseOut(
        empty=estimate is None,
        rotation=_matrix(estimate.rotation) if estimate is not None else None,
        translation=_vector(estimate.translation) if estimate is not None else None,
        method=answer.method,
        largest_violation=answer.violation,
        inner_bound=SampledBoundOut(
            rotation_deg=inner.rotation_deg,
            translation=inner.translation,
            poses_found=inner.poses_found,
            poses_tried=inner.poses_tried,
        )
        if inner is not None
        else None,
        inner_bound_note=answer.inner_note,
        outer_bound=OuterBoundOut(
            certified=outer.certified,
            status=outer.status,
            rotation_deg=_finite_or_none(outer.rotation_deg),
            translation=_finite_or_none(outer.translation),
        )
        if outer is not None
        else None,
        checks=[
            PoseCheckOut(
                rotation=_matrix(check.pose.rotation),
                translation=_vector(check.pose.translation),
                inside=check.membership.inside,
                violations=[_finite_or_none(float(v)) for v in check.membership.violations],
            )
            for check in answer.checks
        ],
    )
