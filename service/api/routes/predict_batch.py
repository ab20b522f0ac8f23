"""POST /v1/predict/batch: several images in one multipart request, each with its own
instances and options; one result or one problem per image, in order.

A problem of one image (its JSON, its decoding, its boxes, no compute slot in time) is
that image's item, with the status it would have had on POST /v1/predict, and the others
are answered. Admission counts images: a batch of n takes n places, so batching cannot get
round CKS_MAX_CONCURRENT_INFERENCES and CKS_MAX_QUEUED_REQUESTS; its images compute in
parallel, one slot and one run each. The body is read, each image's request checked and each
image answered by predict's own steps.
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
import re
from dataclasses import dataclass

from fastapi import APIRouter, Request, Response
from starlette.datastructures import FormData, UploadFile

from service.api.deps import State
from service.api.problems import problem
from service.api.routes.predict import _read_body, _respond, _validated
from service.api.schemas import BatchResponse, PredictParameters
from service.errors import InvalidInput, ServiceError, UnsupportedMediaType
from service.state import ServiceState

router = APIRouter(tags=["prediction"])
log = logging.getLogger(__name__)

_PART = re.compile(r"(image|request)_([0-9]{1,6})")
_IMAGE_PART = {"type": "string", "format": "binary", "description": "JPEG or PNG file"}
_REQUEST_PART = {
    "type": "string",
    "description": "JSON of PredictParameters (instances and options) for the image of the same index",
    "contentMediaType": "application/json",
}
_MULTIPART_SCHEMA = {
    "type": "object",
    "description": "image_i and request_i for i = 0 .. n-1, n <= CKS_MAX_BATCH_IMAGES",
    "required": ["image_0", "request_0"],
    "properties": {"image_0": _IMAGE_PART, "request_0": _REQUEST_PART},
    "patternProperties": {"^image_[0-9]+$": _IMAGE_PART, "^request_[0-9]+$": _REQUEST_PART},
    "additionalProperties": False,
}
_OPENAPI = {
    "requestBody": {"required": True, "content": {"multipart/form-data": {"schema": _MULTIPART_SCHEMA}}},
    "responses": {
        "200": {"description": "One item per image, in order: its result, or its problem (RFC 9457)"},
        "408": {"description": "The body did not arrive within CKS_REQUEST_READ_TIMEOUT_SECONDS"},
        "413": {"description": "The body exceeds CKS_MAX_REQUEST_BYTES"},
        "415": {"description": "Not multipart/form-data"},
        "422": {
            "description": "Parts other than image_i and request_i, an index repeated or beyond"
            " CKS_MAX_BATCH_IMAGES, no parts, or more images than the server admits at once"
        },
        "503": {"description": "Not enough free places for every image of the batch (with Retry-After)"},
    },
}


@dataclass(frozen=True)
class _Part:
    """What the body holds for one index."""

    image: bytes | None
    request: str | None

    def parsed(self, index: int) -> tuple[bytes, PredictParameters]:
        if self.image is None:
            raise InvalidInput(f"multipart part 'image_{index}' (a JPEG or PNG file) is missing")
        if self.request is None:
            raise InvalidInput(
                f"multipart part 'request_{index}' (JSON with instances and options) is missing"
            )
        return self.image, _validated(PredictParameters, self.request)


@router.post(
    "/v1/predict/batch",
    response_model=BatchResponse,
    summary="Keypoint prediction sets for several images in one request, one answer per image",
    openapi_extra=_OPENAPI,
)
async def predict_batch_route(request: Request, state: State) -> Response:
    content_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if content_type != "multipart/form-data":
        raise UnsupportedMediaType(
            f"send multipart/form-data with parts image_0, request_0, image_1, ..., not {content_type!r}"
        )
    state.admission.refuse_if_full()  # not worth receiving
    await _read_body(request, state)  # as predict: a slow client holds no place meanwhile
    parts = await _parts(request, state.settings.max_batch_images)
    capacity = state.admission.capacity
    if len(parts) > capacity:
        raise InvalidInput(
            f"a batch of {len(parts)} images needs {len(parts)} admission places and this server has"
            f" {capacity} (CKS_MAX_CONCURRENT_INFERENCES + CKS_MAX_QUEUED_REQUESTS): send at most"
            f" {capacity} images per batch"
        )
    async with state.admission.admitted(len(parts)):
        answers = (_answer(request, state, index, part) for index, part in enumerate(parts))
        items = await asyncio.gather(*answers)
    # Each item is already JSON (a result as POST /v1/predict writes it, or a problem): joined, not re-parsed.
    return Response(b'{"items":[' + b",".join(items) + b"]}", media_type="application/json")


async def _parts(request: Request, limit: int) -> list[_Part]:
    """The body's parts by index; the whole request is refused only when its layout is wrong."""
    try:
        form = await request.form(max_files=limit, max_fields=limit)
    except Exception as error:  # starlette reports malformed multipart with several types
        raise InvalidInput(
            f"malformed multipart body, or more than {limit} images or requests"
            f" (CKS_MAX_BATCH_IMAGES): {error}"
        ) from error
    try:
        images, requests, problems = await _read_parts(form, limit)
    finally:
        await form.close()  # its spooled files, now rather than when collected
    if problems:
        raise InvalidInput("; ".join(problems[:5]), errors=problems)
    count = max([*images, *requests], default=-1) + 1
    if count == 0:
        raise InvalidInput(
            "the batch is empty: send parts image_0 and request_0 (and image_1, request_1, ...)"
        )
    return [_Part(images.get(index), requests.get(index)) for index in range(count)]


async def _read_parts(form: FormData, limit: int) -> tuple[dict[int, bytes | None], dict[int, str], list]:
    """The images and requests by index, and what is wrong with the parts' names."""
    images: dict[int, bytes | None] = {}
    requests: dict[int, str] = {}
    problems: list[str] = []
    for name, value in form.multi_items():
        match = _PART.fullmatch(name)
        index = int(match.group(2)) if match else -1
        if match is None:
            problems.append(f"unexpected part {name!r}: send image_0, request_0, image_1, request_1, ...")
        elif index >= limit:
            problems.append(
                f"part {name!r}: at most {limit} images per batch, numbered from 0 (CKS_MAX_BATCH_IMAGES)"
            )
        elif index in (images if match.group(1) == "image" else requests):
            problems.append(f"part {name!r} appears more than once")
        elif match.group(1) == "image":
            images[index] = await value.read() if isinstance(value, UploadFile) else None
        else:
            requests[index] = (
                value if isinstance(value, str) else (await value.read()).decode("utf-8", "replace")
            )
    return images, requests, problems


async def _answer(request: Request, state: ServiceState, index: int, part: _Part) -> bytes:
    """One image's item as JSON: its result, or the problem it alone had."""
    try:
        image, parameters = part.parsed(index)
        async with state.admission.slot():  # decoded images exist only inside a slot
            loop = asyncio.get_running_loop()
            context = contextvars.copy_context()  # the pool's thread logs with the request's id
            response = await loop.run_in_executor(
                state.cpu_pool, context.run, _respond, state, image, parameters, False
            )
        return b'{"status":200,"result":' + bytes(response.body) + b"}"
    except ServiceError as error:
        answer = problem(error.status, error.title, error.detail, request, error.errors,
                         extensions=error.extensions)  # fmt: skip
    except Exception:
        log.exception("unhandled error on image %d of a batch", index)
        answer = problem(
            500, "Internal error", "The server failed on this image; the error was logged.", request
        )
    # The same problem body POST /v1/predict would answer, built by the same function.
    return b'{"status":%d,"problem":%s}' % (answer.status_code, bytes(answer.body))
