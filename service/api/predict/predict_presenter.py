"""A Prediction (service.prediction) as the response body of POST /v1/predict: the sets as balls,
ellipses or unbounded, each row's guarantee and stratum, statistics and pose blocks.

The body is built once as plain JSON-ready data in ``PredictResponse``'s shape (field order,
``exclude_if`` fields left out) and written by pydantic-core's own serializer
(``predict_json``): the same bytes ``PredictResponse.model_dump_json`` writes, without
building and validating a model for every keypoint, set and block of every response.
``predict_response`` validates the same data into the models when they are needed (the
PNG drawing, ``predict_png``); tests hold the two paths to the same bytes.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

import numpy as np
from pydantic_core import to_json

from service.api.predict.pose_presenter import pose_out
from service.api.predict.predict_schemas import PredictResponse
from service.api.predict.render import render_prediction
from service.calibration.stratification import Stratum as StratumChoice
from service.conformal import CoverageGuarantee, HeatmapStatistics, ellipse_axes
from service.detector.manifest import Manifest
from service.prediction import Prediction, PredictQuery

Body = dict[str, Any]
UNBOUNDED = {"type": "unbounded", "reason": "too few calibration scores for this epsilon (t = 0)"}


def predict_body(prediction: Prediction, query: PredictQuery, manifest: Manifest) -> Body:
    """The response body of ``prediction``, made for ``query``, as ``PredictResponse`` data."""
    sets, scope = prediction.sets, query.coverage
    regions = _regions(sets.centers, sets.shapes, query.nonconformity)
    guarantees = [_guarantee(guarantee, scope, stratum) for guarantee, stratum in prediction.guarantees]
    stats = _statistics(sets.statistics) if query.include_statistics else [None] * len(regions)
    centers = sets.centers.tolist()
    keypoints = [
        {
            "index": int(channel),
            "name": manifest.keypoints[channel].name,
            "point": centers[row],
            "set": regions[row],
            "guarantee": guarantees[row],
            "statistics": stats[row],
        }
        for row, channel in enumerate(prediction.channel.tolist())
    ]
    poses = [pose_out(p).model_dump() for p in prediction.poses] if prediction.poses is not None else None
    owners = prediction.instance_index.tolist()
    instances = []
    for i, instance in enumerate(query.instances):
        out = {
            "object": instance.object,
            "bbox": instance.bbox,
            "keypoints": [kp for kp, owner in zip(keypoints, owners, strict=True) if owner == i],
        }
        if poses is not None:  # InstanceOut.pose: left out when None
            out["pose"] = poses[i]
        instances.append(out)
    return {
        "model": {"name": prediction.model_name, "hash": prediction.model_hash},
        "calibration": {
            "version": int(prediction.version),
            "nonconformity": query.nonconformity,
            "coverage": scope,
            "epsilon": query.epsilon,
            "delta": query.delta,
        },
        "image": {"width": int(prediction.width), "height": int(prediction.height)},
        "instances": instances,
    }


def predict_json(prediction: Prediction, query: PredictQuery, manifest: Manifest) -> bytes:
    """The response body as ``PredictResponse.model_dump_json`` writes it (pydantic-core; inf and
    nan as null)."""
    return to_json(predict_body(prediction, query, manifest), inf_nan_mode="null")


def predict_response(prediction: Prediction, query: PredictQuery, manifest: Manifest) -> PredictResponse:
    """The response body of ``prediction``, made for ``query``, as validated models."""
    return PredictResponse.model_validate(predict_body(prediction, query, manifest))


def predict_png(prediction: Prediction, query: PredictQuery, manifest: Manifest) -> bytes:
    """The image with the sets (and poses) drawn on it, as a PNG."""
    camera = query.pose.camera if query.pose is not None else None
    return render_prediction(
        prediction.image, predict_response(prediction, query, manifest), camera, manifest
    )


def _regions(centers: np.ndarray, shapes: np.ndarray, kind: str) -> list[Body]:
    semi_minor, semi_major, angles = ellipse_axes(shapes)
    semi_minor, semi_major, angles = semi_minor.tolist(), semi_major.tolist(), angles.tolist()
    regions = []
    for row, (center, shape) in enumerate(zip(centers.tolist(), shapes.tolist(), strict=True)):
        a, b = semi_minor[row], semi_major[row]
        if math.isinf(b):
            regions.append(UNBOUNDED)
        elif a == b and (kind != "cov" or a == 0.0):
            regions.append({"type": "ball", "center": center, "radius": b})
        else:
            regions.append(
                {
                    "type": "ellipse",
                    "center": center,
                    "shape_matrix": shape,
                    "semi_axes": (a, b),
                    "angle_deg": angles[row],
                }
            )
    return regions


def _stratum(choice: StratumChoice) -> Body:
    edges = [{"signal": s, "low": _float(lo), "high": _float(hi)} for s, lo, hi in choice.ranges] or None
    bin_ = None if choice.bin is None else int(choice.bin)
    return {
        "kind": choice.kinds,
        "group": choice.group,
        "bin": bin_,
        "edges": edges,
        "conditional": choice.kinds != "pooled",
        "fallback": choice.fallback,
    }


@lru_cache(maxsize=4096)
def _guarantee(guarantee: CoverageGuarantee, scope: str, stratum: StratumChoice | None = None) -> Body:
    """Shared between rows and requests (cached): never change what it returns."""
    body = {
        "scope": scope,
        "n": int(guarantee.n),
        "t": int(guarantee.t),
        "epsilon": float(guarantee.epsilon),
        "coverage_lower_bound": float(guarantee.marginal_lower),
        "coverage_upper_bound": float(guarantee.marginal_upper),
        "conditional_coverage": {"a": int(guarantee.beta_a), "b": int(guarantee.beta_b)},
        "delta": _float(guarantee.delta),
        "pac_failure_probability": (
            float(guarantee.pac_failure_probability) if guarantee.delta is not None else None
        ),
    }
    if stratum is not None:  # Guarantee.stratum: left out when None
        body["stratum"] = _stratum(stratum)
    return body


def _float(value: float | None) -> float | None:
    return None if value is None else float(value)


def _statistics(statistics: HeatmapStatistics) -> list[Body]:
    gamma = np.sqrt(statistics.variance).tolist()
    probability = statistics.peak_probability.tolist()
    peak, mean = statistics.peak_location.tolist(), statistics.mean.tolist()
    covariance = statistics.covariance.tolist()
    return [
        {
            "peak_probability": probability[i],
            "peak": peak[i],
            "mean": mean[i],
            "gamma": gamma[i],
            "covariance": covariance[i],
        }
        for i in range(len(gamma))
    ]
