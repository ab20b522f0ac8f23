"""POST /v1/predict, /v1/predict/png and /v1/predict/batch: images and boxes in, keypoint sets out.
A batch of n images takes n admission places; each image is answered as it would have been alone."""

from __future__ import annotations

import asyncio
import contextvars
import hashlib
import logging
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from fastapi import APIRouter, Request, Response
from pydantic_core import to_json

from service.api.deps import Predicting, PredictParts
from service.api.feedback.retained_answer import adapted_query, served_request
from service.api.http.problems import problem
from service.api.predict import predict_presenter
from service.api.predict.predict_bodies import BATCH_FORM, BATCH_JSON, PREDICT_FORM, PREDICT_JSON
from service.api.predict.predict_input import (
    BatchItem,
    parse_batch,
    parse_predict,
    predict_query,
    require_batch_media,
)
from service.api.predict.predict_schemas import BatchResponse, PredictParameters, PredictResponse
from service.detector.frames import EncodedFrame
from service.errors import InvalidInput, ServiceError
from service.infra.logs import note_calibration_version

router = APIRouter(tags=["prediction"])
log = logging.getLogger(__name__)

PREDICT_RESPONSES: dict[int | str, dict[str, Any]] = {
    401: {
        "description": "Predict tokens are on ('predict name:token' lines in CKS_ADMIN_TOKENS_FILE) and"
        " the request has no valid predict or admin token"
    },
    408: {"description": "The body did not arrive within 30 s"},
    404: {"description": "calibration_version names a version that does not exist"},
    409: {"description": "The calibration version was scored under other manifest settings"},
    413: {"description": "Body or image too large"},
    415: {"description": "Not JSON or multipart, or not a JPEG/PNG image"},
    422: {"description": "Invalid request: the problem lists what to fix"},
    429: {
        "description": "This caller holds its share of the places while others are served"
        " (CKS_CLIENT_SHARE; with Retry-After)"
    },
    503: {
        "description": "No active calibration, overloaded, stopping, or calibration_version names a version"
        " not in memory while the store is unreachable (with Retry-After)"
    },
}
# Sent as image/png; application/octet-stream is listed too, the type client generators know for bytes.
_BYTES = {"schema": {"type": "string", "format": "binary"}}
_PNG = {"content": {"image/png": _BYTES, "application/octet-stream": _BYTES}}
_BATCH_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {"description": "One item per image, in order: its result, or its problem (RFC 9457)"},
    401: PREDICT_RESPONSES[401],
    408: PREDICT_RESPONSES[408],
    413: {"description": "The body exceeds CKS_MAX_REQUEST_BYTES"},
    415: {"description": "Not JSON or multipart/form-data"},
    422: {
        "description": "Not the documented layout (parts other than image_i and request_i, an image without"
        " its request or the reverse, an index repeated or beyond 16 images, no images, or more"
        " images than the server admits at once)"
    },
    429: PREDICT_RESPONSES[429],
    503: {"description": "Not enough free places for every image of the batch (with Retry-After)"},
}


# POST /v1/predict's JSON example is retained: its answer's prediction_id leads to the feedback
# operation (stateful testers and generated SDKs follow the loop from the example).
_PREDICTION_ID = {"prediction_id": "$response.body#/prediction_id"}
_FEEDBACK_LINK = {"SendFeedback": {"operationId": "send_feedback", "parameters": _PREDICTION_ID}}
_FAILED = "The server failed on this image; the error was logged."  # a batch item's 500
_IMAGE_FORM = "multipart/form-data: the image as a file, its parameters as the JSON part request"


def _json_and_form(path: str, bodies: tuple[dict, dict], form: str, summary: str, links=None, **route: Any):
    """Register the route twice, one request content type each as client generators need: ``path`` with
    the JSON body (200 with ``links``), ``path``/form (``<name>_form``) the multipart; either takes both."""

    def register(endpoint: Callable) -> Callable:
        extra = {"requestBody": bodies[0], **({"responses": {"200": {"links": links}}} if links else {})}
        router.post(path, summary=summary, openapi_extra=extra, **route)(endpoint)
        form_route = {"name": f"{endpoint.__name__}_form", "summary": f"{summary} ({form})", **route}
        router.post(f"{path}/form", openapi_extra={"requestBody": bodies[1]}, **form_route)(endpoint)
        return endpoint

    return register


@_json_and_form(
    "/v1/predict",
    (PREDICT_JSON, PREDICT_FORM),
    _IMAGE_FORM,
    summary="Keypoint prediction sets with a coverage guarantee",
    links=_FEEDBACK_LINK,
    description="The sets as JSON. (`Accept: image/png` here still answers the drawing, as before"
    " POST /v1/predict/png existed; generated clients should call that operation.)",
    response_model=PredictResponse,
    responses=PREDICT_RESPONSES,
)
async def predict(request: Request, parts: Predicting) -> Response:
    accept = request.headers.get("accept", "")
    return await _predict(request, parts, png="image/png" in accept and "application/json" not in accept)


@_json_and_form(
    "/v1/predict/png",
    (PREDICT_JSON, PREDICT_FORM),
    _IMAGE_FORM,
    summary="The image with its keypoint prediction sets drawn on it (PNG)",
    response_class=Response,
    responses={200: {"description": "The image, sets drawn", **_PNG}, **PREDICT_RESPONSES},
)
async def predict_png(request: Request, parts: Predicting) -> Response:
    return await _predict(request, parts, png=True)


async def _predict(request: Request, parts: PredictParts, png: bool) -> Response:
    caller, body = await parts.arrive(request)
    async with parts.admission.admitted(caller):
        image, parameters = await parse_predict(request, body, parts.manifest)
        return await compute(parts, caller, image, parameters, png)


@_json_and_form(
    "/v1/predict/batch",
    (BATCH_JSON, BATCH_FORM),
    "multipart/form-data: parts image_0, request_0, image_1, ...",
    summary="Keypoint prediction sets for several images in one request, one answer per image",
    response_model=BatchResponse,
    responses=_BATCH_RESPONSES,
)
async def predict_batch(request: Request, parts: Predicting) -> Response:
    require_batch_media(request)
    caller, body = await parts.arrive(request)
    items = await parse_batch(request, body, parts.manifest)
    capacity = parts.admission.capacity
    if len(items) > capacity:
        raise InvalidInput(
            f"a batch of {len(items)} images needs {len(items)} admission places and this server has"
            f" {capacity} (CKS_MAX_CONCURRENT_INFERENCES + CKS_MAX_QUEUED_REQUESTS): send at most"
            f" {capacity} images per batch"
        )
    async with parts.admission.admitted(caller, len(items)):
        answers = await asyncio.gather(
            *(_batch_answer(request, parts, caller, i, item) for i, item in enumerate(items))
        )
    # Each answer is JSON already (a result as POST /v1/predict writes it, or a problem): joined.
    return Response(b'{"items":[' + b",".join(answers) + b"]}", media_type="application/json")


async def compute(
    parts: PredictParts, caller: str, image: bytes | EncodedFrame, parameters: PredictParameters, png: bool
) -> Response:
    """Predict and present on the CPU pool in a compute slot; ``image``: a JPEG/PNG file or a frame."""
    async with parts.admission.slot(caller):
        context = contextvars.copy_context()  # the pool's thread logs with the request's id
        answer = (_respond, parts, image, parameters, png, caller)
        return await asyncio.get_running_loop().run_in_executor(parts.pool, context.run, *answer)


def _respond(
    parts: PredictParts, image: bytes | EncodedFrame, parameters: PredictParameters, png: bool, client: str
) -> Response:
    query, adaptive = adapted_query(parts.adaptive, predict_query(parameters), parameters)
    retention = None if png else parts.retention  # a drawing is never retained
    retained = retention is not None and (adaptive is not None or retention.wanted(parameters.retain))
    query = replace(query, retain=True) if retained else query
    prediction = parts.predictor.predict(image, query, whole_image=png)
    note_calibration_version(prediction.version)
    if png:
        png_answer = predict_presenter.predict_png(prediction, query, parts.manifest)
        return Response(png_answer, media_type="image/png")
    answer = predict_presenter.predict_json(prediction, query, parts.manifest)
    if retained:  # prediction_id (and adaptive) follow the answer's last member, as PredictResponse has them
        served = served_request(prediction, query, adaptive)
        sha256 = image.sha256() if isinstance(image, EncodedFrame) else hashlib.sha256(image).hexdigest()
        stream = parameters.stream
        kept = {"prediction_id": retention.retain(prediction.version, served, sha256, stream, client)}
        if adaptive is not None:
            kept["adaptive"] = adaptive.as_dict()
        answer = answer[:-1] + b"," + to_json(kept)[1:]
    return Response(answer, media_type="application/json")


async def _batch_answer(
    request: Request, parts: PredictParts, caller: str, index: int, item: BatchItem
) -> bytes:
    """One image's item as JSON: its result, or the problem it alone had."""
    try:
        image, parameters = item()
        response = await compute(parts, caller, image, parameters, png=False)
        return b'{"status":200,"result":' + bytes(response.body) + b"}"
    except ServiceError as error:
        answer = problem(
            error.status, error.title, error.detail, request, error.errors, extensions=error.extensions
        )
    except Exception:
        log.exception("unhandled error on image %d of a batch", index)
        answer = problem(500, "Internal error", _FAILED, request)
    # The same problem body POST /v1/predict would answer, built by the same function.
    return b'{"status":%d,"problem":%s}' % (answer.status_code, bytes(answer.body))
