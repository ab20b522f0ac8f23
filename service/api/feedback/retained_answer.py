"""A Prediction (service.prediction) as what retention keeps of it (service.feedback.retention)."""

from __future__ import annotations

from dataclasses import replace

from service.api.predict.predict_schemas import PredictParameters
from service.errors import InvalidInput
from service.feedback.adaptive import AdaptiveSets, AdaptiveView
from service.feedback.retention import ServedRequest, finite_or_none, guarantee_values, stratum_name
from service.prediction import Prediction, PredictQuery


def adapted_query(
    adaptive: AdaptiveSets | None, query: PredictQuery, parameters: PredictParameters
) -> tuple[PredictQuery, AdaptiveView | None]:
    """With ``adaptive: true``, the query at the stream's current ACI level (and its state)."""
    if not parameters.adaptive or adaptive is None:
        return query, None
    problems = []
    if parameters.stream is None:
        problems.append("adaptive needs stream (the camera stream whose feedback moves its level)")
    if parameters.delta is not None:
        problems.append("adaptive takes no delta (its guarantee is a long-run bound, not PAC)")
    if query.stratify != "none":
        problems.append("adaptive takes no stratify (one level per stream)")
    if problems:
        raise InvalidInput("; ".join(problems), errors=problems)
    target = {"nonconformity": query.nonconformity, "coverage": query.coverage, "epsilon": query.epsilon}
    view = adaptive.view(adaptive.key(target, parameters.stream), query.epsilon)
    return replace(query, epsilon=view.served_epsilon), view


def served_request(
    prediction: Prediction, query: PredictQuery, adaptive: AdaptiveView | None
) -> ServedRequest:
    """Every row's heatmap statistics, threshold, set centre, guarantee and stratum, and each instance's
    object, box, group and image -> heatmap affine, as plain values."""
    sets, statistics = prediction.sets, prediction.sets.statistics
    assert prediction.affines is not None and sets.thresholds is not None
    columns = {
        "instance": prediction.instance_index.tolist(),
        "channel": prediction.channel.tolist(),
        "uninformative": statistics.uninformative.tolist(),
        "peak": statistics.peak_location.tolist(),
        "peak_probability": statistics.peak_probability.tolist(),
        "mean": statistics.mean.tolist(),
        "covariance": statistics.covariance.tolist(),
        "threshold": [finite_or_none(threshold) for threshold in sets.thresholds.tolist()],
        "center": sets.centers.tolist(),
        "guarantee": [guarantee_values(guarantee) for guarantee, _ in prediction.guarantees],
        "stratum": [stratum_name(stratum) for _, stratum in prediction.guarantees],
    }
    rows = [dict(zip(columns, row, strict=True)) for row in zip(*columns.values(), strict=True)]
    instances = [
        {"object": i.object, "bbox": list(i.bbox), "group": i.group, "affine": affine}
        for i, affine in zip(query.instances, prediction.affines.tolist(), strict=True)
    ]
    asked = {"nonconformity": query.nonconformity, "coverage": query.coverage}
    # with adaptive: the target epsilon, not the level served
    asked |= {"epsilon": query.epsilon if adaptive is None else adaptive.epsilon, "delta": query.delta}
    state = None if adaptive is None else {"key": adaptive.key, **adaptive.as_dict()}
    image = (statistics.heatmap_shape, prediction.width, prediction.height)
    return ServedRequest(asked, instances, rows, *image, adaptive=state)
