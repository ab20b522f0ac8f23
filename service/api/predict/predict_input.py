"""Predict requests as they arrive (JSON with base64, or multipart; a batch's) -> images and queries."""

from __future__ import annotations

import base64
import binascii
import dataclasses
import json
import re
from collections.abc import Callable
from functools import partial
from typing import TypeVar

import numpy as np
from fastapi import Request
from pydantic import BaseModel, ValidationError
from pydantic_core import ErrorDetails
from starlette.datastructures import FormData, UploadFile
from starlette.exceptions import HTTPException

from service.api.predict.predict_schemas import (
    MAX_BATCH_IMAGES,
    PoseRequest,
    PredictJson,
    PredictOptions,
    PredictParameters,
)
from service.detector.manifest import Manifest
from service.errors import InvalidInput, UnsupportedMediaType
from service.pose import Pose, PoseOptions, as_camera_matrix
from service.prediction import Instance, PredictQuery

Model = TypeVar("Model", bound=BaseModel)
_PREFIX = "Value error, "  # pydantic's, before the message of a validator's ValueError
_BATCH_PART = re.compile(r"(image|request)_([0-9]{1,6})")


def validated(
    model: type[Model], raw: str | bytes, manifest: Manifest | None = None, part: str = "the body"
) -> Model:
    """``raw`` JSON (``part`` of the request) as ``model``; 422 listing every problem, unknown objects too."""
    try:
        return model.model_validate_json(raw, context={"manifest": manifest})
    except ValidationError as error:
        raise _schema_refusal(error, part) from error


def _schema_refusal(error: ValidationError, part: str) -> InvalidInput:
    problems = [_problem(e, part) for e in error.errors()]
    return InvalidInput("The request does not match the schema: " + "; ".join(problems[:5]), errors=problems)


def _problem(error: ErrorDetails, part: str) -> str:
    if error["type"] == "json_invalid":
        return (
            f"{part} is not valid JSON ({error['ctx']['error']}): JSON writes names and strings in double"
            """ quotes, e.g. {"instances": [{"object": "duck", "bbox": [235, 217, 67, 64]}]}"""
        )
    # the place as the domain writes it: instances[0].bbox
    where = "".join(f"[{key}]" if isinstance(key, int) else f".{key}" for key in error["loc"])
    return f"{where.lstrip('.')}: {error['msg'].removeprefix(_PREFIX)}"


def media_type(request: Request) -> str:
    return request.headers.get("content-type", "").split(";")[0].strip().lower()


async def parse_predict(request: Request, body: bytes, manifest: Manifest) -> tuple[bytes, PredictParameters]:
    """The image and the parameters of a POST /v1/predict body (already read whole)."""
    content_type = media_type(request)
    if content_type == "application/json":
        return _from_json(body, manifest)
    if content_type == "multipart/form-data":
        return await _parse_multipart(request, manifest)
    raise UnsupportedMediaType(
        f"send application/json (image_base64) or multipart/form-data (image + request), not {content_type!r}"
    )


def _from_json(body: bytes | str, manifest: Manifest) -> tuple[bytes, PredictParameters]:
    return _with_image(validated(PredictJson, body, manifest))


def _with_image(parameters: PredictJson) -> tuple[bytes, PredictJson]:
    try:
        image = base64.b64decode(parameters.image_base64, validate=True)
    except (binascii.Error, ValueError) as error:
        raise InvalidInput(f"image_base64 is not valid base64: {error}") from error
    return image, parameters


_PREDICT_PARTS = "send the parts image (the JPEG or PNG file) and request (the JSON parameters), once each"


async def _parse_multipart(request: Request, manifest: Manifest) -> tuple[bytes, PredictParameters]:
    form = await _read_form(request, 2, _PREDICT_PARTS)  # request may come as a file (a Blob) or a field
    try:
        names = [name for name, _ in form.multi_items()]
        for name in names:
            if name not in ("image", "request"):
                raise InvalidInput(f"unexpected multipart part {name!r}: {_PREDICT_PARTS}")
            if names.count(name) > 1:
                raise InvalidInput(f"multipart part {name!r} appears more than once: {_PREDICT_PARTS}")
        image, raw = form.get("image"), form.get("request")
        if image is None:
            raise InvalidInput("multipart part 'image' (a JPEG or PNG file) is missing")
        if not isinstance(image, UploadFile):
            raise InvalidInput("multipart part 'image' must be a file (a part with a filename), not a field")
        if raw is None:
            raise InvalidInput("multipart part 'request' (JSON with instances and options) is missing")
        parameters = validated(PredictParameters, await _text(raw), manifest, "the multipart part 'request'")
        return await image.read(), parameters
    finally:
        await form.close()  # its spooled files, now rather than when collected


async def _read_form(request: Request, parts: int, layout: str) -> FormData:
    """The form, of at most ``parts`` files (a JSON Blob is one) and ``parts`` fields; 422 if malformed."""
    try:
        return await request.form(max_files=parts, max_fields=parts)
    except HTTPException as error:  # starlette's 400 for a body it cannot parse
        if str(error.detail).startswith("Too many"):
            raise InvalidInput(f"the multipart body has too many parts: {layout}") from error
        raise InvalidInput(f"malformed multipart body: {error.detail}") from error
    except Exception as error:  # python-multipart reports other malformations with several types
        raise InvalidInput(f"malformed multipart body: {error}") from error


async def _text(part: str | UploadFile) -> str:
    """A JSON part as text: a plain field, or a file part of any type (application/json, a Blob's)."""
    return part if isinstance(part, str) else (await part.read()).decode("utf-8", "replace")


def predict_query(parameters: PredictParameters) -> PredictQuery:
    """The schema's parameters as the domain's query (checked against the image by the domain)."""
    asked = {field.name for field in dataclasses.fields(PredictQuery)}  # stream, adaptive: the API's
    options = {name: getattr(parameters, name) for name in PredictOptions.model_fields if name in asked}
    instances = tuple(Instance(i.object, i.bbox, i.group) for i in parameters.instances)
    pose = None if parameters.pose is None else _pose_options(parameters.pose)
    return PredictQuery(**{**options, "instances": instances, "pose": pose})


def _pose_options(request: PoseRequest) -> PoseOptions:
    checks: dict[int, list[Pose]] = {}
    for check in request.check:
        pose = Pose(np.array(check.rotation, dtype=np.float64), np.array(check.translation, dtype=np.float64))
        checks.setdefault(check.instance, []).append(pose)
    camera = as_camera_matrix(request.K)  # the schema has checked K already
    return PoseOptions(camera, request.samples, request.outer_bound, request.outer_programs, checks)


# One image of a batch: called, its image and parameters, or the problem of that image alone.
BatchItem = Callable[[], tuple[bytes, PredictParameters]]


def require_batch_media(request: Request) -> None:
    """415 unless the batch comes as JSON or multipart (checked before its body is received)."""
    if media_type(request) not in ("application/json", "multipart/form-data"):
        raise UnsupportedMediaType(
            'send application/json ({"items": [...]}) or multipart/form-data (parts image_0, request_0,'
            f" image_1, ...), not {media_type(request)!r}"
        )


async def parse_batch(request: Request, body: bytes, manifest: Manifest) -> list[BatchItem]:
    """The images of a POST /v1/predict/batch body; only a wrong layout refuses the whole request."""
    if media_type(request) == "application/json":
        return _json_batch(body, manifest)
    layout = f"at most {MAX_BATCH_IMAGES} images and {MAX_BATCH_IMAGES} requests: image_0, request_0, ..."
    form = await _read_form(request, 2 * MAX_BATCH_IMAGES, layout)  # requests may come as files (Blobs)
    try:
        images, requests, problems = await _batch_parts(form)
    finally:
        await form.close()  # its spooled files, now rather than when collected
    count = max([*images, *requests], default=-1) + 1
    problems += [  # image_i and request_i come together, i = 0 .. count-1
        f"part '{kind}_{i}' is missing: send image_i and request_i together, for i = 0 .. n-1"
        for i in range(count)
        for kind, parts in (("image", images), ("request", requests))
        if i not in parts
    ]
    if problems:
        raise InvalidInput("; ".join(problems[:5]), errors=problems)
    if count == 0:
        raise InvalidInput(
            "the batch is empty: send parts image_0 and request_0 (and image_1, request_1, ...)"
        )
    return [partial(_multipart_item, i, images[i], requests[i], manifest) for i in range(count)]


def _json_batch(body: bytes, manifest: Manifest) -> list[BatchItem]:
    """Each item parsed once, by the schema, from a plain UTF-8 ``{"items": [...]}``; any other body the
    slow way (whole, then each item written again), which words every refusal."""
    raw_items = _raw_items(body)
    if raw_items is None or not 0 < len(raw_items) <= MAX_BATCH_IMAGES:
        return _parsed_json_batch(body, manifest)
    items: list[BatchItem] = []
    for raw in raw_items:
        try:
            parameters = PredictJson.model_validate_json(raw, context={"manifest": manifest})
        except ValidationError as error:
            if any(e["type"] == "json_invalid" for e in error.errors()):
                return _parsed_json_batch(body, manifest)
            items.append(partial(_raise, _schema_refusal(error, "the body")))
        except Exception as error:  # raised when its item is answered, as the other way does
            items.append(partial(_raise, error))
        else:
            items.append(partial(_with_image, parameters))
    return items


def _raise(error: Exception) -> tuple[bytes, PredictParameters]:
    raise error


_ENVELOPE_HEAD = re.compile(rb'[ \t\n\r]*\{[ \t\n\r]*"items"[ \t\n\r]*:[ \t\n\r]*\[')
_ENVELOPE_TAIL = re.compile(rb"[ \t\n\r]*\}[ \t\n\r]*")
_MARK = re.compile(rb'["\[\]{},]')  # a string's quote, or what nests or separates items


def _raw_items(body: bytes) -> list[bytes] | None:
    """The raw JSON of each item of a ``{"items": [...]}`` body in UTF-8, split at the commas
    between them (items are checked by their parser); None for anything else."""
    head = _ENVELOPE_HEAD.match(body)
    if head is None or b"\0" in body:  # NUL: UTF-16 or UTF-32, which json.loads detects
        return None
    items, depth, start, at = [], 0, head.end(), head.end()
    while (token := _MARK.search(body, at)) is not None:
        mark, at = token.group(), token.end()
        if mark == b'"':
            at = _string_end(body, at)
        elif mark in (b"[", b"{"):
            depth += 1
        elif mark == b",":
            if not depth:
                items.append(body[start : token.start()])
                start = at
        elif depth:
            depth -= 1
        elif mark == b"]":
            items.append(body[start : token.start()])
            return items if _ENVELOPE_TAIL.fullmatch(body, at) else None
        else:  # the envelope closed before its list
            return None
        if at < 0:
            return None
    return None


def _string_end(body: bytes, at: int) -> int:
    """Past the quote that closes the string whose text starts at ``at`` (-1: none); found with
    bytes.find, as fast as a base64 image is long."""
    while (quote := body.find(b'"', at)) >= 0:
        before = quote
        while body[before - 1] == ord("\\"):
            before -= 1
        if (quote - before) % 2 == 0:  # not escaped
            return quote + 1
        at = quote + 1
    return -1


def _parsed_json_batch(body: bytes, manifest: Manifest) -> list[BatchItem]:
    layout = 'send {"items": [...]}: an object whose only member, items, lists POST /v1/predict JSON bodies'
    try:
        envelope = json.loads(body)
    except ValueError as error:
        raise InvalidInput(f"the body is not JSON ({error}): {layout}") from error
    items = envelope.get("items") if isinstance(envelope, dict) else None
    if not isinstance(items, list) or set(envelope) != {"items"}:
        raise InvalidInput(layout)
    if not items:
        raise InvalidInput("the batch is empty: send at least one item")
    if len(items) > MAX_BATCH_IMAGES:
        raise InvalidInput(f"{len(items)} items: at most {MAX_BATCH_IMAGES} images per batch")
    return [partial(_from_json, json.dumps(item), manifest) for item in items]


async def _batch_parts(form: FormData) -> tuple[dict[int, bytes | None], dict[int, str], list]:
    """The images and requests by index, and what is wrong with the parts' names."""
    images: dict[int, bytes | None] = {}
    requests: dict[int, str] = {}
    problems: list[str] = []
    for name, value in form.multi_items():
        match = _BATCH_PART.fullmatch(name)
        index = int(match.group(2)) if match else -1
        if match is None:
            problems.append(f"unexpected part {name!r}: send image_0, request_0, image_1, request_1, ...")
        elif index >= MAX_BATCH_IMAGES:
            problems.append(f"part {name!r}: at most {MAX_BATCH_IMAGES} images per batch, numbered from 0")
        elif index in (images if match.group(1) == "image" else requests):
            problems.append(f"part {name!r} appears more than once")
        elif match.group(1) == "image":
            images[index] = await value.read() if isinstance(value, UploadFile) else None
        else:
            requests[index] = await _text(value)
    return images, requests, problems


def _multipart_item(
    index: int, image: bytes | None, raw: str, manifest: Manifest
) -> tuple[bytes, PredictParameters]:
    if image is None:
        raise InvalidInput(f"multipart part 'image_{index}' must be a file (a JPEG or PNG with a filename)")
    return image, validated(PredictParameters, raw, manifest, f"the multipart part 'request_{index}'")
