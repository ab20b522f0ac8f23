"""POST /v1/predict/frame's request: the frame's size, its pixels whole or as regions, raw or encoded."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, StrictInt

from service.api.predict.predict_schemas import PredictParameters, StrictBody

Encoding = Literal["rgb8", "bgr8", "mono8", "jpeg", "png"]
_ENCODING = (
    "rgb8, bgr8, mono8: raw 8-bit pixels as ROS sensor_msgs/Image names them, row-major, no row"
    " padding (height * width * 3 or 1 bytes); jpeg, png: a file of exactly this size"
)
MAX_SIDE = 2**31 - 1


class FrameIn(StrictBody):
    """The camera frame the boxes and the answer's pixels refer to."""

    width: StrictInt = Field(gt=0, le=MAX_SIDE, description="the full frame's width in pixels")
    height: StrictInt = Field(gt=0, le=MAX_SIDE, description="the full frame's height in pixels")
    encoding: Encoding | None = Field(
        None,
        description="with the whole frame as the one `pixels` part: its encoding (" + _ENCODING + ");"
        " left out when regions are sent",
    )


class RegionIn(StrictBody):
    """A rectangle of the frame (ROS sensor_msgs/RegionOfInterest), sent as one `pixels` part."""

    x_offset: StrictInt = Field(ge=0, le=MAX_SIDE, description="its left column in the frame")
    y_offset: StrictInt = Field(ge=0, le=MAX_SIDE, description="its top row in the frame")
    width: StrictInt = Field(gt=0, le=MAX_SIDE, description="x_offset + width <= frame.width")
    height: StrictInt = Field(gt=0, le=MAX_SIDE, description="y_offset + height <= frame.height")
    encoding: Encoding = Field(description=_ENCODING)
    instances: list[StrictInt] = Field(
        min_length=1,
        description="indexes into instances whose crops this region serves; each instance is served by"
        " exactly one region, which must hold its crop context (docs/predict.md)",
    )


class FrameRequest(PredictParameters):
    """The JSON part `request` of POST /v1/predict/frame."""

    frame: FrameIn
    regions: list[RegionIn] | None = Field(
        None,
        min_length=1,
        description="the frame's regions, each sent as a `pixels` part in this order; left out when the"
        " whole frame is the one `pixels` part (frame.encoding)",
    )
