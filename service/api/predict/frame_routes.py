"""POST /v1/predict/frame: a camera frame's pixels, whole or as the boxes' regions, raw or as JPEG/PNG,
to POST /v1/predict's answer for the same pixels (docs/predict.md, Frames), computed as that one is."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request, Response

from service.api.deps import Predicting
from service.api.http.contract import SCHEMAS
from service.api.predict.frame_input import LAYOUT, parse_frame, require_multipart
from service.api.predict.predict_bodies import EXAMPLE_INSTANCES, form_body
from service.api.predict.predict_routes import PREDICT_RESPONSES, compute
from service.api.predict.predict_schemas import PredictResponse

router = APIRouter(tags=["prediction"])

# A request the service answers as it is: a 16 x 16 grey frame, raw mono8, sent whole (one byte a
# pixel, so the example's text is its pixels).
_EXAMPLE = {
    "request": {"instances": EXAMPLE_INSTANCES, "frame": {"width": 16, "height": 16, "encoding": "mono8"}},
    "pixels": ["~" * 16 * 16],
}
_PIXELS = {
    "type": "array",
    "minItems": 1,
    "items": {"type": "string", "format": "binary"},
    "description": "one part per regions[i], in order, or one part, the whole frame (frame.encoding): raw"
    " pixels (height * width * channels bytes, row-major) or a JPEG or PNG file",
}
# pixels keep the default encoding (application/octet-stream): generators that read a list of types
# literally send the whole array as one part
FRAME_BODY = form_body(
    {
        "type": "object",
        "description": LAYOUT,
        "required": ["request", "pixels"],
        "properties": {"request": {"$ref": SCHEMAS.format(model="FrameRequest")}, "pixels": _PIXELS},
        "additionalProperties": False,
    },
    ["request"],
    _EXAMPLE,
)
_RESPONSES: dict[int | str, dict[str, Any]] = {
    **PREDICT_RESPONSES,
    413: {
        "description": "The body exceeds CKS_MAX_REQUEST_BYTES, the frame CKS_MAX_IMAGE_PIXELS, or its"
        " decoded pixels 256 MiB"
    },
    415: {"description": "Not multipart/form-data, or a part that is not the JPEG/PNG its encoding says"},
    422: {
        "description": "Invalid request: the problem lists what to fix (parts, a region outside the frame"
        " or missing a margin of a box's crop context, bytes that disagree with a shape, a box no region"
        " serves)"
    },
}


@router.post(
    "/v1/predict/frame",
    response_model=PredictResponse,
    summary="Keypoint prediction sets for a camera frame sent whole or as its boxes' regions, raw or encoded",
    description="The answer POST /v1/predict gives for the same pixels, byte for byte, in full-frame"
    " pixels, when each region holds its boxes' crop contexts (docs/predict.md, Frames).",
    responses=_RESPONSES,
    openapi_extra={"requestBody": FRAME_BODY},
)
async def predict_frame(request: Request, parts: Predicting) -> Response:
    content_type = request.headers.get("content-type", "")
    require_multipart(content_type)
    caller, body = await parts.arrive(request)
    async with parts.admission.admitted(caller):
        frame, parameters = parse_frame(content_type, body, parts.manifest)
        return await compute(parts, caller, frame, parameters, png=False)
