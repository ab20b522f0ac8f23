"""POST /v1/feedback/{prediction_id}: the true points of a retained prediction, judged and stored."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter

from service.api.deps import (
    ADMIN_RESPONSES,
    FEEDBACK_RESPONSES,
    Adaptive,
    Admin,
    Config,
    FeedbackSender,
    Model,
    NewVersionRules,
    Registry,
    Retaining,
    Store,
    Trail,
)
from service.api.feedback.feedback_schemas import (
    FeedbackIn,
    FeedbackOut,
    FieldCalibrationIn,
    FieldCalibrationOut,
    JudgedKeypoint,
)
from service.calibration.intake import UploadOptions
from service.feedback.field_calibration import FieldSelection, calibrate_from_feedback
from service.feedback.labels import InstanceLabels, record_feedback

router = APIRouter(tags=["feedback"])


@router.post(
    "/v1/feedback/{prediction_id}",
    response_model=FeedbackOut,
    summary="The true points of a retained prediction: judged against the sets served, stored",
    responses={
        **FEEDBACK_RESPONSES,
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
    body: FeedbackIn,
    operator: FeedbackSender,
    store: Store,
    trail: Trail,
    model: Model,
    config: Config,
    adaptive: Adaptive,
    retention: Retaining,
) -> FeedbackOut:
    labels = [InstanceLabels(i.instance, tuple(i.keypoints)) for i in body.instances]
    max_age = config.feedback.max_age_seconds
    names = [keypoint.name for keypoint in model.manifest.keypoints]
    judged = await asyncio.to_thread(
        record_feedback,
        store,
        trail,
        operator,
        prediction_id,
        labels,
        max_age,
        names,
        adaptive,
        retention,
    )
    rows = judged.prediction.record["rows"]
    keypoints = [
        JudgedKeypoint(
            instance=rows[row["row"]]["instance"],
            index=rows[row["row"]]["channel"],
            name=names[rows[row["row"]]["channel"]],
            covered=row["covered"],
            scores=row["scores"],
        )
        for row in judged.rows
    ]
    return FeedbackOut(
        prediction_id=prediction_id,
        calibration_version=judged.prediction.version,
        labelled=len(keypoints),
        covered=sum(k.covered for k in keypoints),
        keypoints=keypoints,
    )


@router.post(
    "/v1/admin/field-calibrations",
    response_model=FieldCalibrationOut,
    status_code=201,
    summary="A calibration version from labelled feedback (no zip): the scores an upload of the same images"
    " and labels gives, through the same duplicate rules, guardrails and audit trail",
    responses={
        **ADMIN_RESPONSES,
        404: {"description": "append_to names no version"},
        409: {"description": "Repeats (use dedupe), a version equal to a stored one, or scored differently"},
        422: {"description": "No labelled feedback matches, or force without a reason"},
    },
)
async def calibrate_from_field(
    body: FieldCalibrationIn,
    operator: Admin,
    store: Store,
    model: Model,
    registry: Registry,
    trail: Trail,
    rules: NewVersionRules,
    config: Config,
) -> FieldCalibrationOut:
    options = UploadOptions(**body.model_dump(exclude={"stream", "served_by"}))
    selection = FieldSelection(body.stream, body.served_by)
    limit = config.feedback.max_retained
    arguments = (store, model, registry.scores, selection, options, operator, rules, trail, limit)
    outcome = await asyncio.to_thread(calibrate_from_feedback, *arguments)
    registry.refresh_now()
    return FieldCalibrationOut(
        version=outcome.info.number, activated=outcome.activated, summary=outcome.summary
    )
