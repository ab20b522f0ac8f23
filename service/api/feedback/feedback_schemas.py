"""Request and response bodies of the feedback API (pydantic v2)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

Label = tuple[float, float, int]


class InstanceLabelsIn(BaseModel):
    model_config = ConfigDict(extra="forbid")

    instance: int = Field(ge=0, description="index into the prediction's instances")
    keypoints: list[Label] = Field(
        description="[x, y, v] per keypoint of the instance's object, in image pixels; v = 0 not labelled,"
        " 1 occluded, 2 visible (COCO)",
    )


class FeedbackIn(BaseModel):
    """The true points of some or all of a retained prediction's instances."""

    model_config = ConfigDict(extra="forbid")

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
