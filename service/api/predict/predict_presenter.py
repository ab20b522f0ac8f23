"""A Prediction (service.prediction) as the response body of POST /v1/predict: the sets as balls,
ellipses or unbounded, each row's guarantee and stratum, statistics and pose blocks, as the
response models of predict_schemas (the one definition of the answer's shape)."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from service.api.predict import predict_schemas as schemas
from service.api.predict.render import render_prediction
from service.calibration.stratification import Stratum as StratumChoice
from service.conformal import CoverageGuarantee, HeatmapStatistics, ellipse_axes
from service.detector.manifest import Manifest
from service.pose import PoseSets
from service.prediction import Prediction, PredictQuery

UNBOUNDED = schemas.UnboundedSet(reason="too few calibration scores for this epsilon (t = 0)")


def predict_response(
    prediction: Prediction, query: PredictQuery, manifest: Manifest
) -> schemas.PredictResponse:
    """The response body of ``prediction``, made for ``query``."""
    sets, scope = prediction.sets, query.coverage
    regions = _regions(sets.centers, sets.shapes, query.nonconformity)
    variant = manifest.variant_name
    guarantees = [_guarantee(g, scope, variant, stratum) for g, stratum in prediction.guarantees]
    stats = _statistics(sets.statistics) if query.include_statistics else [None] * len(regions)
    centers = sets.centers.tolist()
    asked = {"nonconformity": query.nonconformity, "epsilon": query.epsilon, "delta": query.delta}
    keypoints = [
        schemas.KeypointOut(
            index=channel,
            name=manifest.keypoints[channel].name,
            point=centers[row],
            set=regions[row],
            guarantee=guarantees[row],
            statistics=stats[row],
        )
        for row, channel in enumerate(prediction.channel.tolist())
    ]
    poses = [_pose(p) for p in prediction.poses] if prediction.poses is not None else None
    owners = prediction.instance_index.tolist()
    instances = [
        schemas.InstanceOut(
            object=instance.object,
            bbox=instance.bbox,
            keypoints=[kp for kp, owner in zip(keypoints, owners, strict=True) if owner == i],
            pose=None if poses is None else poses[i],
        )
        for i, instance in enumerate(query.instances)
    ]
    return schemas.PredictResponse(
        model=schemas.ModelRef(name=prediction.model_name, hash=prediction.model_hash, variant=variant),
        calibration=schemas.CalibrationRef(version=prediction.version, coverage=scope, **asked),
        image=schemas.ImageInfo(width=prediction.width, height=prediction.height),
        instances=instances,
    )


def predict_json(prediction: Prediction, query: PredictQuery, manifest: Manifest) -> bytes:
    """The response body as JSON (inf and nan as null)."""
    return predict_response(prediction, query, manifest).model_dump_json().encode()


def predict_png(prediction: Prediction, query: PredictQuery, manifest: Manifest) -> bytes:
    """The image with the sets (and poses) drawn on it, as a PNG."""
    camera = query.pose.camera if query.pose is not None else None
    response = predict_response(prediction, query, manifest)
    return render_prediction(prediction.image, response, camera, manifest)


def _regions(centers: np.ndarray, shapes: np.ndarray, kind: str) -> list[schemas.PredictionSet]:
    axes = (values.tolist() for values in ellipse_axes(shapes))  # semi-minor a, semi-major b, angle
    regions: list[schemas.PredictionSet] = []
    for center, shape, a, b, angle in zip(centers.tolist(), shapes.tolist(), *axes, strict=True):
        if math.isinf(b):
            regions.append(UNBOUNDED)
        elif a == b and (kind != "cov" or a == 0.0):
            regions.append(schemas.BallSet(center=center, radius=b))
        else:
            region = schemas.EllipseSet(center=center, shape_matrix=shape, semi_axes=(a, b), angle_deg=angle)
            regions.append(region)
    return regions


def _stratum(choice: StratumChoice) -> schemas.Stratum:
    edges = [schemas.SignalRange(signal=s, low=low, high=high) for s, low, high in choice.ranges] or None
    same = {"group": choice.group, "bin": choice.bin, "fallback": choice.fallback}
    return schemas.Stratum(kind=choice.kinds, edges=edges, conditional=choice.kinds != "pooled", **same)


@lru_cache(maxsize=4096)
def _guarantee(
    guarantee: CoverageGuarantee, scope: str, variant: str, stratum: StratumChoice | None = None
) -> schemas.Guarantee:
    """Shared between rows and requests (cached): never change what it returns."""
    return schemas.Guarantee(
        scope=scope,
        model_variant=variant,
        n=guarantee.n,
        t=guarantee.t,
        epsilon=guarantee.epsilon,
        coverage_lower_bound=guarantee.marginal_lower,
        coverage_upper_bound=guarantee.marginal_upper,
        conditional_coverage=schemas.BetaLaw(a=guarantee.beta_a, b=guarantee.beta_b),
        delta=guarantee.delta,
        pac_failure_probability=guarantee.pac_failure_probability if guarantee.delta is not None else None,
        stratum=None if stratum is None else _stratum(stratum),
    )


def _statistics(statistics: HeatmapStatistics) -> list[schemas.KeypointStatistics]:
    gamma = np.sqrt(statistics.variance).tolist()
    columns = (statistics.peak_probability, statistics.peak_location, statistics.mean, statistics.covariance)
    return [
        schemas.KeypointStatistics(peak_probability=p, peak=peak, mean=mean, gamma=g, covariance=covariance)
        for p, peak, mean, covariance, g in zip(*(c.tolist() for c in columns), gamma, strict=True)
    ]


def _finite_or_none(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def _pose(answer: PoseSets) -> schemas.PoseOut:
    estimate, inner, outer = answer.estimate, answer.inner, answer.outer
    checks = [
        schemas.PoseCheckOut(
            rotation=check.pose.rotation.tolist(),
            translation=check.pose.translation.tolist(),
            inside=check.membership.inside,
            violations=[_finite_or_none(float(v)) for v in check.membership.violations],
        )
        for check in answer.checks
    ]
    return schemas.PoseOut(
        empty=estimate is None,
        rotation=None if estimate is None else estimate.rotation.tolist(),
        translation=None if estimate is None else estimate.translation.tolist(),
        method=answer.method,
        largest_violation=answer.violation,
        inner_bound=None if inner is None else vars(inner),
        inner_bound_note=answer.inner_note,
        outer_bound=schemas.OuterBoundOut(
            certified=outer.certified,
            status=outer.status,
            rotation_deg=_finite_or_none(outer.rotation_deg),
            translation=_finite_or_none(outer.translation),
            **_tightness(answer),
        )
        if outer is not None
        else None,
        checks=checks,
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
