"""Feedback on a retained prediction: true image points in, a judged and stored label out
(404 unknown, 410 expired, 422 bad labels, 409 labelled already): each labelled point is scored
from the kept heatmap statistics as a calibration upload would, and stored with its verdicts.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from typing import Any

import numpy as np

from calibration_store import LabelOutcome, RetainedPrediction
from service.conformal import NONCONFORMITY_SCORES, HeatmapStatistics, get_nonconformity_score
from service.detector.crop import apply_affines
from service.errors import Conflict, Gone, InvalidInput, NotFound
from service.feedback.adaptive import AdaptiveSets
from service.feedback.retention import Retention, retained_at
from service.feedback.verdicts import covered_units, verdicts
from service.infra.audit_trail import AuditTrail, Operator, written

VISIBILITIES = (0, 1, 2)  # COCO: not labelled, occluded, visible
#: how long after its prediction a row may still be on its way to the store (written in the background)
IN_FLIGHT_S = 5.0
POLL_S = 0.05


@dataclass(frozen=True)
class InstanceLabels:
    """The true ``(x, y, v)`` per keypoint of one instance, image pixels (v = 0: not labelled)."""

    instance: int
    keypoints: tuple[tuple[float, float, int], ...]


@dataclass(frozen=True)
class Judged:
    """A stored label: per labelled row its scores and whether the served set covered it."""

    prediction: RetainedPrediction
    labels: dict[str, Any]

    @property
    def rows(self) -> list[dict[str, Any]]:
        return self.labels["rows"]


def record_feedback(
    store: Any,
    audit: AuditTrail,
    operator: Operator,
    prediction_id: str,
    instances: Sequence[InstanceLabels],
    max_age_s: float,
    keypoint_names: list[str],
    adaptive: AdaptiveSets | None = None,
    retention: Retention | None = None,
) -> Judged:
    """The feedback use case; ``retention``: this process's, whose queued answers go first."""
    if retention is not None:
        retention.flush()
    retained = find_retained(store, prediction_id, max_age_s)
    points = check_labels(retained.record, instances)
    rows = judge(retained.record, points)
    given = [{"instance": i.instance, "keypoints": [list(k) for k in i.keypoints]} for i in instances]
    labels = {"instances": given, "rows": rows}
    covered = sum(row["covered"] for row in rows)
    details = {"prediction_id": prediction_id, "keypoints": len(rows), "covered": covered}
    entry = audit.entry(operator, "feedback", "labelled", version=retained.version, details=details)
    counted = verdicts(replace(retained, labels=labels), keypoint_names)
    outcome = store.label_prediction(prediction_id, labels, operator.name, datetime.now(UTC), entry, counted)
    if outcome is LabelOutcome.ALREADY_LABELLED:
        refused = {"reason": "labelled"}
        audit.record(operator, "feedback", "refused", version=retained.version, details=refused)
        raise Conflict(
            f"prediction {prediction_id} has its feedback already; each prediction is labelled once"
        )
    if outcome is LabelOutcome.MISSING:
        raise _gone(prediction_id)
    written(entry)
    served = retained.record.get("adaptive")
    if served is not None and adaptive is not None:
        misses = [not covered for _, _, covered in covered_units(retained.record, rows)]
        adaptive.learn(served["key"], served["epsilon"], misses, served.get("steps"))
    return Judged(retained, labels)


def find_retained(store: Any, prediction_id: str, max_age_s: float) -> RetainedPrediction:
    """The retained prediction, 404 or 410; one made moments ago may still be on its way."""
    made = retained_at(prediction_id)
    retained = store.retained_prediction(prediction_id) if made is not None else None
    while retained is None and made is not None and _age_s(made) < IN_FLIGHT_S:
        time.sleep(POLL_S)
        retained = store.retained_prediction(prediction_id)
    if retained is not None:
        if retained.labels is None and retained.expires_at < datetime.now(UTC):
            raise _gone(prediction_id)
        return retained
    oldest = store.oldest_retained() if made is not None else None
    if made is not None and (_age_s(made) > max_age_s or oldest is None or made < oldest):
        raise _gone(prediction_id)
    raise NotFound(
        f"no retained prediction {prediction_id!r}: send the prediction_id of an answer to a predict"
        ' request made with "retain": true (or sampled by CKS_FEEDBACK_RETAIN_SHARE)'
    )


def _age_s(made: datetime) -> float:
    return (datetime.now(UTC) - made).total_seconds()


def _gone(prediction_id: str) -> Gone:
    return Gone(
        f"prediction {prediction_id} is no longer kept: feedback must arrive within"
        " CKS_FEEDBACK_MAX_AGE_SECONDS, and the oldest predictions go first beyond CKS_FEEDBACK_MAX_RETAINED"
    )


def check_labels(record: dict[str, Any], instances: Sequence[InstanceLabels]) -> dict[int, np.ndarray]:
    """Row index -> (x, y) image point of every labelled keypoint; 422 listing every problem."""
    rows_of: dict[int, list[int]] = {}
    for row, values in enumerate(record["rows"]):
        rows_of.setdefault(values["instance"], []).append(row)
    problems, points, seen = [], {}, set()
    width, height = record["image"]["width"], record["image"]["height"]
    for i, labels in enumerate(instances):
        where = f"instances[{i}]"
        if labels.instance not in rows_of:
            problems.append(
                f"{where}.instance {labels.instance} is not an instance of the prediction"
                f" (0 to {len(record['instances']) - 1})"
            )
            continue
        if labels.instance in seen:
            problems.append(f"{where}.instance {labels.instance} is labelled twice")
        seen.add(labels.instance)
        rows = rows_of[labels.instance]
        if len(labels.keypoints) != len(rows):
            obj = record["instances"][labels.instance]["object"]
            problems.append(
                f"{where}.keypoints has {len(labels.keypoints)} entries but object {obj!r} has {len(rows)}"
                " keypoints: give [x, y, v] for each, v = 0 for those not labelled"
            )
            continue
        for j, (row, (x, y, v)) in enumerate(zip(rows, labels.keypoints, strict=True)):
            if v not in VISIBILITIES:
                problems.append(f"{where}.keypoints[{j}]: visibility {v} is not 0, 1 or 2")
            elif v and not (math.isfinite(x) and math.isfinite(y)):
                problems.append(f"{where}.keypoints[{j}]: x and y must be finite numbers")
            elif v and not (0 <= x <= width and 0 <= y <= height):
                problems.append(
                    f"{where}.keypoints[{j}]: ({x:g}, {y:g}) lies outside the {width}x{height} image"
                )
            elif v:
                points[row] = np.array([x, y], dtype=np.float64)
    if not problems and not points:
        problems.append("no keypoint is labelled (every visibility is 0): nothing to learn from")
    if problems:
        raise InvalidInput("; ".join(problems[:5]), errors=problems)
    return points


def judge(record: dict[str, Any], points: dict[int, np.ndarray]) -> list[dict[str, Any]]:
    """Per labelled row: its scores under every function and whether the served set covered it."""
    rows = sorted(points)
    values = [record["rows"][r] for r in rows]
    statistics = kept_statistics(record, values)
    affines = np.array([record["instances"][v["instance"]]["affine"] for v in values], dtype=np.float64)
    heatmap_points = apply_affines(affines, np.stack([points[r] for r in rows]))
    scores = {
        kind: get_nonconformity_score(kind).score(statistics, heatmap_points).tolist()
        for kind in NONCONFORMITY_SCORES
    }
    served = record["query"]["nonconformity"]
    judged = []
    for k, (row, kept) in enumerate(zip(rows, values, strict=True)):
        threshold = math.inf if kept["threshold"] is None else kept["threshold"]
        row_scores = {kind: scores[kind][k] for kind in scores}
        judged.append({"row": row, "scores": row_scores, "covered": bool(row_scores[served] <= threshold)})
    return judged


def kept_statistics(record: dict[str, Any], rows: Sequence[dict[str, Any]]) -> HeatmapStatistics:
    """The heatmap statistics of ``rows`` as they were computed when the prediction was served."""

    def column(name: str) -> np.ndarray:
        return np.array([r[name] for r in rows], dtype=np.float64)

    return HeatmapStatistics(
        heatmap_shape=tuple(record["heatmap_shape"]),
        uninformative=np.array([r["uninformative"] for r in rows], dtype=bool),
        peak_location=column("peak"),
        peak_probability=column("peak_probability"),
        mean=column("mean"),
        covariance=column("covariance"),
    )
