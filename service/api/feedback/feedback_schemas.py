"""Request and response bodies of the feedback API (pydantic v2)."""

from __future__ import annotations

from pydantic import BaseModel, Field, field_validator

from service.api.predict.predict_schemas import MAX_VERSION, StrictBody

Label = tuple[float, float, int]


class InstanceLabelsIn(StrictBody):
    instance: int = Field(ge=0, description="index into the prediction's instances")
    keypoints: list[Label] = Field(
        description="[x, y, v] per keypoint of the instance's object, in image pixels; v = 0 not labelled,"
        " 1 occluded, 2 visible (COCO); triples, not COCO's flat list x1, y1, v1, x2, ..."
    )

    @field_validator("keypoints", mode="before")
    @classmethod
    def _triples(cls, keypoints: object) -> object:
        """COCO's flat list is what teams have: named in the refusal, with the way to fix it."""
        if isinstance(keypoints, list) and keypoints and all(isinstance(v, int | float) for v in keypoints):
            raise ValueError(
                "send triples [x, y, v], not COCO's flat list x1, y1, v1, x2, ...: group its numbers in"
                " threes, [[x1, y1, v1], [x2, y2, v2], ...]"
            )
        return keypoints


class FeedbackIn(StrictBody):
    """The true points of some or all of a retained prediction's instances."""

    instances: list[InstanceLabelsIn] = Field(min_length=1, max_length=1000)


class JudgedKeypoint(BaseModel):
    instance: int
    index: int = Field(description="manifest keypoint index")
    name: str
    covered: bool = Field(description="the true point lay in the set served")
    scores: dict[str, float] = Field(description="its nonconformity score under each function")


class FeedbackOut(BaseModel):
    prediction_id: str
    calibration_version: int
    labelled: int = Field(description="keypoints labelled")
    covered: int = Field(description="of them, inside the set served")
    keypoints: list[JudgedKeypoint]


class GroupCoverageOut(BaseModel):
    level: str = Field(
        description="version (all keypoints), object, keypoint, stream, group (the caller's) or stratum"
        " (the Mondrian stratum that answered, with stratify)"
    )
    name: str
    version: int
    guarantee: str = Field(
        description="exchangeable (the calibration's), or adaptive (ACI sets: no floor and no alarm; their"
        " long-run bound is in each answer's adaptive block)"
    )
    nonconformity: str
    coverage: str = Field(description="keypoint, or object (a unit is a fully labelled instance)")
    epsilon: float
    delta: float | None
    labelled: int = Field(description="units labelled (keypoints, or instances with coverage object)")
    covered: int = Field(description="of them, inside the set served")
    looks: int = Field(
        description="independent looks that voted (frames of one scene are one look; a look votes once"
        " complete: when a label of its stream's next look is read)"
    )
    look_mean: float | None = Field(description="mean vote (a look's share of covered units, all its frames)")
    lower: float = Field(description="anytime-valid lower confidence bound of the votes' mean")
    upper: float = Field(description="anytime-valid upper confidence bound")
    promised: float = Field(description="1 - epsilon")
    floor: float = Field(
        description="the least coverage the version promises: the alarm_level/2 quantile of its Beta"
        " law (1 - epsilon with a PAC delta)"
    )
    alarm: bool = Field(
        description="coverage proven below what the calibration gives: every rung of a ladder of floors"
        " over its Beta law (around floor) crossed (docs/feedback.md)"
    )


class LiveCoverageOut(BaseModel):
    alarm_level: float = Field(
        description="CKS_FEEDBACK_ALARM_LEVEL: each group's probability of a false alarm, however long"
        " and often watched (the bounds form a confidence sequence at this level); exact for a group of"
        " one threshold, at most K times it for K thresholds whose coverages do not move together"
    )
    alarm: bool
    groups: list[GroupCoverageOut]


class FieldCalibrationIn(StrictBody):
    """Labelled feedback made a calibration version: which labels, and the upload's options."""

    stream: str | None = Field(None, max_length=64, description="only this camera stream's labels")
    served_by: int | None = Field(None, ge=1, description="only labels of answers served by this version")
    name: str | None = Field(None, description="the source batch's name (default feedback-<sha256>)")
    note: str = ""
    append_to: int | None = Field(
        None, ge=1, le=MAX_VERSION, description="new version = this one + the labels"
    )
    activate: bool = False
    force: bool = Field(False, description="activate past the guardrails (needs reason)")
    reason: str = ""
    dedupe: bool = Field(False, description="drop instances already counted instead of refusing")
    allow_duplicate: bool = Field(False, description="store a version equal to a stored one (reason)")


class FieldCalibrationOut(BaseModel):
    version: int
    activated: bool
    summary: dict = Field(description="as a calibration job's result: instances, added, rejections, problems")
