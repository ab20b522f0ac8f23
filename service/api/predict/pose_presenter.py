"""Pose answers out: service.pose's results as the API's schemas."""

from __future__ import annotations

import math

import numpy as np

from service.api.predict.predict_schemas import OuterBoundOut, PoseCheckOut, PoseOut, SampledBoundOut
from service.pose import PoseSets


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
        inner_bound=None if inner is None else SampledBoundOut.model_validate(inner, from_attributes=True),
        inner_bound_note=answer.inner_note,
        outer_bound=OuterBoundOut(
            certified=outer.certified,
            status=outer.status,
            rotation_deg=_finite_or_none(outer.rotation_deg),
            translation=_finite_or_none(outer.translation),
            **_tightness(answer),
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


def _ratio(outer: float | None, inner: float) -> float | None:
    return outer / inner if outer is not None and math.isfinite(outer) and inner > 0 else None


def _tightness(answer: PoseSets) -> dict[str, float | None]:
    """outer / inner per quantity, for certified bounds with an inner bound to compare with."""
    inner, outer = answer.inner, answer.outer
    if inner is None or outer is None or not outer.certified or outer.empty:
        return {}
    return {
        "rotation_over_inner": _ratio(outer.rotation_deg, inner.rotation_deg),
        "translation_over_inner": _ratio(outer.translation, inner.translation),
    }
