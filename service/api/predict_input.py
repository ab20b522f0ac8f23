"""Predict requests as they arrive (JSON with base64, or multipart) -> image bytes and a domain
``PredictQuery``; the batch route's parts, one request per index."""

from __future__ import annotations

import base64
import binascii
import re
from typing import TypeVar

import numpy as np
from fastapi import Request
from pydantic import BaseModel, ValidationError
from starlette.datastructures import FormData, UploadFile

from service.api.predict_schemas import PoseRequest, PredictJson, PredictParameters
from service.errors import InvalidInput, UnsupportedMediaType
from service.pose import Pose, PoseOptions, as_camera_matrix
from service.prediction import Instance, PredictQuery

Model = TypeVar("Model", bound=BaseModel)
_BATCH_PART = re.compile(r"(image|request)_([0-9]{1,6})")


def validated(model: type[Model], raw: str | bytes) -> Model:
    """``raw`` JSON as ``model``; 422 listing every problem the schema finds."""
    try:
        return model.model_validate_json(raw)
    except ValidationError as error:
        problems = [f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in error.errors()]
        raise InvalidInput(
            "The request does not match the schema: " + "; ".join(problems[:5]), errors=problems
        ) from error


def media_type(request: Request) -> str:
    return request.headers.get("content-type", "").split(";")[0].strip().lower()


async def parse_predict(request: Request, body: bytes) -> tuple[bytes, PredictParameters]:
    """The image and the parameters of a POST /v1/predict body (already read whole)."""
    content_type = media_type(request)
    if content_type == "application/json":
        parameters = validated(PredictJson, body)
        try:
            image = base64.b64decode(parameters.image_base64, validate=True)
        except (binascii.Error, ValueError) as error:
            raise InvalidInput(f"image_base64 is not valid base64: {error}") from error
        return image, parameters
    if content_type == "multipart/form-data":
        return await _parse_multipart(request)
    raise UnsupportedMediaType(
        f"send application/json (image_base64) or multipart/form-data (image + request), not {content_type!r}"
    )


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
        return await image.read(), validated(PredictParameters, raw)
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


BatchItem = tuple[bytes | None, str | None]  # one index's image and request JSON, either may be missing


def require_batch_media(request: Request) -> None:
    """415 unless the batch comes as multipart (checked before its body is received)."""
    if media_type(request) != "multipart/form-data":
        raise UnsupportedMediaType(
            "send multipart/form-data with parts image_0, request_0, image_1, ...,"
            f" not {media_type(request)!r}"
        )


async def parse_batch(request: Request, limit: int) -> list[BatchItem]:
    """The parts of a POST /v1/predict/batch body by index; the whole request is refused only
    when its layout is wrong."""
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
    return [(images.get(index), requests.get(index)) for index in range(count)]


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


def batch_item(index: int, item: BatchItem) -> tuple[bytes, PredictParameters]:
    """One index's image and parameters, or the problem of that index alone."""
    image, raw = item
    if image is None:
        raise InvalidInput(f"multipart part 'image_{index}' (a JPEG or PNG file) is missing")
    if raw is None:
        raise InvalidInput(f"multipart part 'request_{index}' (JSON with instances and options) is missing")
    return image, validated(PredictParameters, raw)
