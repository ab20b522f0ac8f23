"""Predict requests as they arrive (JSON with base64, or multipart) -> image bytes and a domain
``PredictQuery``; the batch route's parts, one request per index."""

from __future__ import annotations

import base64
import binascii
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

from service.api.predict.predict_schemas import PoseRequest, PredictJson, PredictParameters
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
    """``raw`` JSON (``part`` of the request) as ``model``; 422 listing every problem the schema
    finds, and every instance whose object is not one of ``manifest``'s."""
    try:
        return model.model_validate_json(raw, context={"manifest": manifest})
    except ValidationError as error:
        problems = [_problem(e, part) for e in error.errors()]
        raise InvalidInput(
            "The request does not match the schema: " + "; ".join(problems[:5]), errors=problems
        ) from error


def _problem(error: ErrorDetails, part: str) -> str:
    if error["type"] == "json_invalid":
        return (
            f"{part} is not valid JSON ({error['ctx']['error']}): JSON writes names and strings in double"
            """ quotes, e.g. {"instances": [{"object": "duck", "bbox": [235, 217, 67, 64]}]}"""
        )
    return f"{_where(error['loc'])}: {error['msg'].removeprefix(_PREFIX)}"


def _where(loc: tuple) -> str:
    """A problem's place as the domain writes it: instances[0].bbox."""
    return "".join(f"[{part}]" if isinstance(part, int) else f".{part}" for part in loc).lstrip(".")


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
    parameters = validated(PredictJson, body, manifest)
    try:
        image = base64.b64decode(parameters.image_base64, validate=True)
    except (binascii.Error, ValueError) as error:
        raise InvalidInput(f"image_base64 is not valid base64: {error}") from error
    return image, parameters


async def _parse_multipart(request: Request, manifest: Manifest) -> tuple[bytes, PredictParameters]:
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
        return await image.read(), validated(PredictParameters, raw, manifest, "the multipart part 'request'")
    finally:
        await form.close()  # its spooled files, now rather than when collected


def predict_query(parameters: PredictParameters) -> PredictQuery:
    """The schema's parameters as the domain's query (checked against the model by the domain)."""
    instances = tuple(Instance(i.object, i.bbox, i.group) for i in parameters.instances)
    return PredictQuery(
        instances=instances,
        epsilon=parameters.epsilon,
        nonconformity=parameters.nonconformity,
        coverage=parameters.coverage,
        delta=parameters.delta,
        calibration_version=parameters.calibration_version,
        include_statistics=parameters.include_statistics,
        stratify=parameters.stratify,
        group_fallback=parameters.group_fallback,
        pose=None if parameters.pose is None else _pose_options(parameters.pose),
    )


def _pose_options(request: PoseRequest) -> PoseOptions:
    checks: dict[int, list[Pose]] = {}
    for check in request.check:
        pose = Pose(np.array(check.rotation, dtype=np.float64), np.array(check.translation, dtype=np.float64))
        checks.setdefault(check.instance, []).append(pose)
    camera = as_camera_matrix(request.K)  # the schema has checked K already
    return PoseOptions(
        camera, request.samples, request.outer_bound, request.outer_splits, checks, request.outer_programs
    )


# One image of a batch: called, its image and parameters, or the problem of that image alone.
BatchItem = Callable[[], tuple[bytes, PredictParameters]]
_BATCH_MEDIA = ("application/json", "multipart/form-data")


def require_batch_media(request: Request) -> None:
    """415 unless the batch comes as JSON or multipart (checked before its body is received)."""
    if media_type(request) not in _BATCH_MEDIA:
        raise UnsupportedMediaType(
            'send application/json ({"items": [...]}) or multipart/form-data (parts image_0, request_0,'
            f" image_1, ...), not {media_type(request)!r}"
        )


async def parse_batch(request: Request, body: bytes, limit: int, manifest: Manifest) -> list[BatchItem]:
    """The images of a POST /v1/predict/batch body; the whole request is refused only when its
    layout is wrong."""
    if media_type(request) == "application/json":
        return _json_batch(body, limit, manifest)
    try:
        form = await request.form(max_files=limit, max_fields=limit)
    except Exception as error:  # starlette reports malformed multipart with several types
        raise InvalidInput(
            f"malformed multipart body, or more than {limit} images or requests"
            f" (CKS_MAX_BATCH_IMAGES): {error}"
        ) from error
    try:
        images, requests, problems = await _batch_parts(form, limit)
    finally:
        await form.close()  # its spooled files, now rather than when collected
    if problems:
        raise InvalidInput("; ".join(problems[:5]), errors=problems)
    count = max([*images, *requests], default=-1) + 1
    if count == 0:
        raise InvalidInput(
            "the batch is empty: send parts image_0 and request_0 (and image_1, request_1, ...)"
        )
    return [partial(_multipart_item, i, images.get(i), requests.get(i), manifest) for i in range(count)]


def _json_batch(body: bytes, limit: int, manifest: Manifest) -> list[BatchItem]:
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
    if len(items) > limit:
        raise InvalidInput(f"{len(items)} items: at most {limit} images per batch (CKS_MAX_BATCH_IMAGES)")
    return [partial(_from_json, json.dumps(item), manifest) for item in items]


async def _batch_parts(form: FormData, limit: int) -> tuple[dict[int, bytes | None], dict[int, str], list]:
    """The images and requests by index, and what is wrong with the parts' names."""
    images: dict[int, bytes | None] = {}
    requests: dict[int, str] = {}
    problems: list[str] = []
    for name, value in form.multi_items():
        match = _BATCH_PART.fullmatch(name)
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


def _multipart_item(
    index: int, image: bytes | None, raw: str | None, manifest: Manifest
) -> tuple[bytes, PredictParameters]:
    if image is None:
        raise InvalidInput(f"multipart part 'image_{index}' (a JPEG or PNG file) is missing")
    if raw is None:
        raise InvalidInput(f"multipart part 'request_{index}' (JSON with instances and options) is missing")
    return image, validated(PredictParameters, raw, manifest, f"the multipart part 'request_{index}'")
