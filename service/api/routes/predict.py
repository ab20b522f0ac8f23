"""POST /v1/predict: an image and boxes in, keypoint prediction sets out (JSON or a PNG)."""

from __future__ import annotations

import asyncio
import base64
import binascii
import contextvars

import numpy as np
from fastapi import APIRouter, Request, Response
from pydantic import ValidationError
from starlette.datastructures import UploadFile
from starlette.formparsers import MultiPartParser

from service.api.body import BodyPace, read_limited_body
from service.api.deps import State
from service.api.multipart import plain_form
from service.api.pose_presenter import pose_options
from service.api.predict_presenter import predict_body, predict_json
from service.api.render import render_prediction
from service.api.schemas import PredictJson, PredictParameters, PredictResponse
from service.errors import InvalidInput, Unavailable, UnsupportedMediaType
from service.image_decoding import decode_image
from service.logs import note_calibration_version
from service.prediction import check_instances, predict
from service.state import ServiceState

router = APIRouter(tags=["prediction"])

_MULTIPART_SCHEMA = {
    "type": "object",
    "required": ["image", "request"],
    "properties": {
        "image": {"type": "string", "format": "binary", "description": "JPEG or PNG file"},
        "request": {
            "type": "string",
            "description": "JSON of PredictParameters: instances and options",
            "contentMediaType": "application/json",
        },
    },
}
_OPENAPI = {
    "requestBody": {
        "required": True,
        "content": {
            "application/json": {"schema": {"$ref": "#/components/schemas/PredictJson"}},
            "multipart/form-data": {"schema": _MULTIPART_SCHEMA},
        },
    },
    "responses": {
        "200": {"content": {"image/png": {"schema": {"type": "string", "format": "binary"}}}},
        "408": {"description": "The body did not arrive within CKS_REQUEST_READ_TIMEOUT_SECONDS"},
        "409": {"description": "The calibration version was scored under other manifest settings"},
        "413": {"description": "Body or image too large"},
        "415": {"description": "Not JSON or multipart, or not a JPEG/PNG image"},
        "422": {"description": "Invalid request; the problem lists what to fix"},
        "503": {
            "description": "No active calibration, overloaded, or calibration_version names a version"
            " not in memory while the store is unreachable (with Retry-After)"
        },
    },
}


def _validated(model: type[PredictParameters], raw: str | bytes) -> PredictParameters:
    try:
        return model.model_validate_json(raw)
    except ValidationError as error:
        problems = [f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in error.errors()]
        raise InvalidInput(
            "The request does not match the schema: " + "; ".join(problems[:5]), errors=problems
        ) from error


async def _parse(request: Request, body: bytes) -> tuple[bytes, PredictParameters]:
    content_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if content_type == "application/json":
        parameters = _validated(PredictJson, body)
        try:
            image = base64.b64decode(parameters.image_base64, validate=True)
        except (binascii.Error, ValueError) as error:
            raise InvalidInput(f"image_base64 is not valid base64: {error}") from error
        return image, parameters
    if content_type == "multipart/form-data":
        return _parse_plain_multipart(request, body) or await _parse_multipart(request)
    raise UnsupportedMediaType(
        f"send application/json (image_base64) or multipart/form-data (image + request), not {content_type!r}"
    )


async def _read_body(request: Request, state: State) -> bytes:
    """The body within CKS_MAX_REQUEST_BYTES, paced, its bytes counted against
    CKS_MAX_RECEIVING_BYTES while it arrives."""
    settings = state.settings
    pace = BodyPace.from_settings(
        settings, settings.request_read_timeout_seconds, "CKS_REQUEST_READ_TIMEOUT_SECONDS"
    )
    limit = settings.max_request_bytes
    with state.admission.receiving() as count:
        return await read_limited_body(request, limit, "CKS_MAX_REQUEST_BYTES", pace, count)


def _parse_plain_multipart(request: Request, body: bytes) -> tuple[bytes, PredictParameters] | None:
    """The image and parameters of a plain body (``plain_form``) holding just the file ``image``
    and the field ``request``, read as Starlette would; None: anything else, for Starlette."""
    parts = plain_form(request.headers.get("content-type", ""), body)
    if parts is None or parts.keys() != {b"image", b"request"}:
        return None
    image, raw = parts[b"image"], parts[b"request"]
    if image.filename is None or raw.filename is not None or len(raw.data) > MultiPartParser.max_part_size:
        return None
    try:
        text = raw.data.decode("utf-8")
    except UnicodeDecodeError:  # Starlette falls back to latin-1
        return None
    return image.data, _validated(PredictParameters, text)


async def _parse_multipart(request: Request) -> tuple[bytes, PredictParameters]:
    try:
        form = await request.form(max_files=1, max_fields=2)
    except Exception as error:  # starlette reports malformed multipart with several types
        raise InvalidInput(f"malformed multipart body: {error}") from error
    try:
        image, raw = form.get("image"), form.get("request")
        if not isinstance(image, UploadFile):
            raise InvalidInput("multipart part 'image' (a JPEG or PNG file) is missing")
        if raw is None:
            raise InvalidInput("multipart part 'request' (JSON with instances and options) is missing")
        raw = raw if isinstance(raw, str) else (await raw.read()).decode("utf-8", "replace")
        return await image.read(), _validated(PredictParameters, raw)
    finally:
        await form.close()  # its spooled files, now rather than when collected


def _wants_png(request: Request) -> bool:
    accept = request.headers.get("accept", "")
    return "image/png" in accept and "application/json" not in accept


@router.post(
    "/v1/predict",
    response_model=PredictResponse,
    summary="Keypoint prediction sets with a coverage guarantee",
    openapi_extra=_OPENAPI,
)
async def predict_route(request: Request, state: State) -> Response:
    try:
        state.admission.refuse_if_full()  # not worth receiving
        body = await _read_body(request, state)  # a slow client holds no place meanwhile
        async with state.admission.admitted():
            image_bytes, parameters = await _parse(request, body)
            async with state.admission.slot():  # decoded images exist only inside a slot
                loop = asyncio.get_running_loop()
                context = contextvars.copy_context()  # the pool's thread logs with the request's id
                return await loop.run_in_executor(
                    state.cpu_pool, context.run, _respond, state, image_bytes, parameters, _wants_png(request)
                )
    except asyncio.CancelledError:  # uvicorn cancels what is left when a shutdown's grace period ends
        raise Unavailable(
            "the service stopped before this request was done (CKS_SHUTDOWN_GRACE_SECONDS): send it again",
            headers={"Retry-After": "1", "Connection": "close"},
        ) from None


def _respond(state: ServiceState, image_bytes: bytes, parameters: PredictParameters, png: bool) -> Response:
    manifest = state.detector.manifest
    image = decode_image(image_bytes, state.settings.max_image_pixels, state.settings.max_decoded_bytes)
    height, width = image.shape[:2]
    check_instances(parameters.instances, manifest, width, height, state.settings.max_instances)
    pose = pose_options(parameters, manifest)  # refused before the model runs
    prediction = predict(state, image, parameters, pose, instances_checked=True)
    body = predict_body(prediction, parameters, manifest)
    note_calibration_version(prediction.version)
    if png:
        camera = np.asarray(parameters.pose.K) if parameters.pose is not None else None
        drawn = render_prediction(image, PredictResponse.model_validate(body), camera, manifest)
        return Response(drawn, media_type="image/png")
    return Response(predict_json(body), media_type="application/json")
