"""A Prediction (service.prediction) as the response body of POST /v1/predict: the sets as balls,
ellipses or unbounded, each row's guarantee and stratum, statistics and pose blocks."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from service.api.pose_presenter import pose_out
from service.api.schemas import (
    BallSet,
    BetaLaw,
    CalibrationRef,
    EllipseSet,
    Guarantee,
    ImageInfo,
    InstanceOut,
    KeypointOut,
    KeypointStatistics,
    ModelRef,
    PredictParameters,
    PredictResponse,
    SignalRange,
    Stratum,
    UnboundedSet,
)
from service.calibration.stratification import Stratum as StratumChoice
from service.conformal import CoverageGuarantee, HeatmapStatistics, ellipse_axes
from service.detector.manifest import Manifest
from service.prediction import Prediction


def predict_response(
    prediction: Prediction, parameters: PredictParameters, manifest: Manifest
) -> PredictResponse:
    """The response body of ``prediction``, made for ``parameters``."""
    sets, scope = prediction.sets, parameters.coverage
    regions = _regions(sets.centers, sets.shapes, parameters.nonconformity)
    guarantees = [_guarantee(guarantee, scope, stratum) for guarantee, stratum in prediction.guarantees]
    stats = _statistics(sets.statistics) if parameters.include_statistics else [None] * len(regions)
    keypoints = [
        KeypointOut(
            index=int(channel),
            name=manifest.keypoints[channel].name,
            point=(float(sets.centers[row, 0]), float(sets.centers[row, 1])),
            set=regions[row],
            guarantee=guarantees[row],
            statistics=stats[row],
        )
        for row, channel in enumerate(prediction.channel)
    ]
    poses = [pose_out(p) for p in prediction.poses] if prediction.poses is not None else None
    owners = prediction.instance_index
    instances = [
        InstanceOut(
            object=instance.object,
            bbox=instance.bbox,
            keypoints=[kp for kp, owner in zip(keypoints, owners, strict=True) if owner == i],
            pose=poses[i] if poses is not None else None,
        )
        for i, instance in enumerate(parameters.instances)
    ]
    return PredictResponse(
        model=ModelRef(name=prediction.model_name, hash=prediction.model_hash),
        calibration=CalibrationRef(
            version=prediction.version,
            nonconformity=parameters.nonconformity,
            coverage=scope,
            epsilon=parameters.epsilon,
            delta=parameters.delta,
        ),
        image=ImageInfo(width=prediction.width, height=prediction.height),
        instances=instances,
    )


def _regions(centers: np.ndarray, shapes: np.ndarray, kind: str) -> list:
    semi_minor, semi_major, angles = ellipse_axes(shapes)
    regions = []
    for row, center in enumerate(centers):
        c = (float(center[0]), float(center[1]))
        a, b = float(semi_minor[row]), float(semi_major[row])
        if math.isinf(b):
            regions.append(UnboundedSet(reason="too few calibration scores for this epsilon (t = 0)"))
        elif a == b and (kind != "cov" or a == 0.0):
            regions.append(BallSet(center=c, radius=b))
        else:
            shape = shapes[row]
            regions.append(
                EllipseSet(
                    center=c,
                    shape_matrix=(
                        (float(shape[0, 0]), float(shape[0, 1])),
                        (float(shape[1, 0]), float(shape[1, 1])),
                    ),
                    semi_axes=(a, b),
                    angle_deg=float(angles[row]),
                )
            )
    return regions


def _stratum(choice: StratumChoice) -> Stratum:
    edges = [SignalRange(signal=s, low=low, high=high) for s, low, high in choice.ranges] or None
    return Stratum(kind=choice.kinds, group=choice.group, bin=choice.bin, edges=edges,
                   conditional=choice.kinds != "pooled", fallback=choice.fallback)  # fmt: skip


@lru_cache(maxsize=4096)
def _guarantee(guarantee: CoverageGuarantee, scope: str, stratum: StratumChoice | None = None) -> Guarantee:
    return Guarantee(
        scope=scope,
        n=guarantee.n,
        t=guarantee.t,
        epsilon=guarantee.epsilon,
        coverage_lower_bound=guarantee.marginal_lower,
        coverage_upper_bound=guarantee.marginal_upper,
        conditional_coverage=BetaLaw(a=guarantee.beta_a, b=guarantee.beta_b),
        delta=guarantee.delta,
        pac_failure_probability=guarantee.pac_failure_probability if guarantee.delta is not None else None,
        stratum=None if stratum is None else _stratum(stratum),
    )


def _statistics(statistics: HeatmapStatistics) -> list[KeypointStatistics]:
    covariance = statistics.covariance
    gamma = np.sqrt(statistics.variance)
    return [
        KeypointStatistics(
            peak_probability=float(statistics.peak_probability[i]),
            peak=tuple(statistics.peak_location[i]),
            mean=tuple(statistics.mean[i]),
            gamma=float(gamma[i]),
            covariance=(tuple(covariance[i, 0]), tuple(covariance[i, 1])),
        )
        for i in range(len(gamma))
    ]
