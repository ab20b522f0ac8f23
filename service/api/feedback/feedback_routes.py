"""POST /v1/feedback/{prediction_id}: the true points of a retained prediction, judged and stored; what
they make: field calibrations, and GET /v1/admin/coverage/live (the sets' coverage, with its alarm)."""

from __future__ import annotations

import asyncio
from dataclasses import asdict

from fastapi import APIRouter

from service.api import deps
from service.api.feedback import feedback_schemas as schemas
from service.calibration.intake import UploadOptions
from service.feedback.field_calibration import FieldSelection, calibrate_from_feedback
from service.feedback.labels import InstanceLabels, record_feedback

router = APIRouter(tags=["feedback"])
admin_router = APIRouter(prefix="/v1/admin", tags=["admin"], responses=deps.ADMIN_RESPONSES)


@router.post(
    "/v1/feedback/{prediction_id}",
    response_model=schemas.FeedbackOut,
    summary="The true points of a retained prediction: judged against the sets served, stored",
    responses={
        **deps.FEEDBACK_RESPONSES,
        404: {"description": "No prediction was retained under this id"},
        409: {"description": "This prediction has its feedback already"},
        410: {
            "description": "The prediction is no longer kept (CKS_FEEDBACK_MAX_AGE_SECONDS, _MAX_RETAINED)"
        },
        422: {"description": "The labels do not fit the prediction: the problem lists what to fix"},
    },
)
async def send_feedback(
    prediction_id: str,
    body: schemas.FeedbackIn,
    operator: deps.FeedbackSender,
    store: deps.Store,
    trail: deps.Trail,
    model: deps.Model,
    config: deps.Config,
    adaptive: deps.Adaptive,
    retention: deps.Retaining,
) -> schemas.FeedbackOut:
    labels = [InstanceLabels(i.instance, tuple(i.keypoints)) for i in body.instances]
    names = [keypoint.name for keypoint in model.manifest.keypoints]
    arguments = (prediction_id, labels, config.feedback.max_age_seconds, names, adaptive, retention)
    judged = await asyncio.to_thread(record_feedback, store, trail, operator, *arguments)
    served = judged.prediction.record["rows"]
    keypoints = []
    for row in judged.rows:
        instance, channel = served[row["row"]]["instance"], served[row["row"]]["channel"]
        keypoints.append(schemas.JudgedKeypoint(instance=instance, index=channel, name=names[channel], **row))
    counts = {"labelled": len(keypoints), "covered": sum(k.covered for k in keypoints)}
    version = judged.prediction.version
    return schemas.FeedbackOut(
        prediction_id=prediction_id, calibration_version=version, keypoints=keypoints, **counts
    )


@router.post(
    "/v1/admin/field-calibrations",
    response_model=schemas.FieldCalibrationOut,
    status_code=201,
    summary="A calibration version from labelled feedback (no zip): the scores an upload of the same images"
    " and labels gives, through the same duplicate rules, guardrails and audit trail",
    responses={
        **deps.ADMIN_RESPONSES,
        404: {"description": "append_to names no version"},
        409: {"description": "Repeats (use dedupe), a version equal to a stored one, or scored differently"},
        422: {"description": "No labelled feedback matches, or force without a reason"},
    },
)
async def calibrate_from_field(
    body: schemas.FieldCalibrationIn,
    operator: deps.Admin,
    store: deps.Store,
    model: deps.Model,
    registry: deps.Registry,
    trail: deps.Trail,
    rules: deps.NewVersionRules,
    config: deps.Config,
) -> schemas.FieldCalibrationOut:
    options = UploadOptions(**body.model_dump(exclude={"stream", "served_by"}))
    selection = FieldSelection(body.stream, body.served_by)
    arguments = (selection, options, operator, rules, trail, config.feedback.max_retained)
    outcome = await asyncio.to_thread(calibrate_from_feedback, store, model, registry.scores, *arguments)
    registry.refresh_now()
    version, activated = outcome.info.number, outcome.activated
    return schemas.FieldCalibrationOut(version=version, activated=activated, summary=outcome.summary)


@admin_router.get(
    "/coverage/live",
    response_model=schemas.LiveCoverageOut,
    summary="Coverage of the sets served, from feedback labels: per version, object, keypoint, stream,"
    " group; an anytime-valid confidence sequence and an alarm when coverage is proven below the promise",
)
async def live_coverage(reader: deps.LiveCoverage, who: deps.Admin) -> schemas.LiveCoverageOut:
    groups = await asyncio.to_thread(reader.report)
    alarm = any(g.alarm for g in groups)
    return schemas.LiveCoverageOut(alarm_level=reader.level, alarm=alarm, groups=[asdict(g) for g in groups])
