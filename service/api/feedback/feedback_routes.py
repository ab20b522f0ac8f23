"""POST /v1/feedback/{prediction_id}: the true points of a retained prediction, judged and stored."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter

from service.api.deps import FEEDBACK_RESPONSES, Adaptive, Config, FeedbackSender, Model, Store, Trail
from service.api.feedback.feedback_schemas import FeedbackIn, FeedbackOut, JudgedKeypoint
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
) -> FeedbackOut:
    labels = [InstanceLabels(i.instance, tuple(i.keypoints)) for i in body.instances]
    max_age = config.feedback.feedback_max_age_seconds
    judged = await asyncio.to_thread(
        record_feedback, store, trail, operator, prediction_id, labels, max_age, adaptive
    )
    rows = judged.prediction.record["rows"]
    names = model.manifest.keypoints
    keypoints = [
        JudgedKeypoint(
            instance=rows[row["row"]]["instance"],
            index=rows[row["row"]]["channel"],
            name=names[rows[row["row"]]["channel"]].name,
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
