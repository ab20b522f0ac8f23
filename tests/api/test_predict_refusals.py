"""Every bad predict request gets a precise 4xx as RFC 9457 problem+json (never a 5xx).

Runs against the service with small limits (image pixels, request bytes, instances).
"""

from __future__ import annotations

import json
import math
import struct
import zlib

import cv2
import numpy as np
import pytest

from tests.api.in_process import InProcess
from tests.predict_client import predict_json, predict_multipart
from tests.samples import Sample, b64
from tests.service_calls import assert_problem

SMALL = (320, 240)  # width, height of a synthetic image under every limit


def png(width: int, height: int) -> bytes:
    ok, encoded = cv2.imencode(".png", np.full((height, width, 3), 127, np.uint8))
    assert ok
    return encoded.tobytes()


def png_header_only(width: int, height: int) -> bytes:
    """A PNG signature and IHDR claiming a size, and no pixel data at all."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    chunk = struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    return b"\x89PNG\r\n\x1a\n" + chunk


@pytest.fixture(scope="module")
def small_image() -> bytes:
    return png(*SMALL)


@pytest.fixture(scope="module")
def object_name(manifest: dict) -> str:
    return manifest["objects"][0]["name"]


@pytest.fixture(scope="module")
def instance(object_name: str) -> dict:
    return {"object": object_name, "bbox": [100, 60, 80, 90]}


def raw_json_post(api: InProcess, text: str, content_type: str = "application/json"):
    return api.client.post("/v1/predict", content=text.encode(), headers={"Content-Type": content_type})


@pytest.mark.parametrize(
    "content_type", ["text/plain", "application/xml", "application/x-www-form-urlencoded", None]
)
def test_not_json_or_multipart_is_415(limited_api: InProcess, content_type: str | None) -> None:
    headers = {} if content_type is None else {"Content-Type": content_type}
    response = limited_api.client.post("/v1/predict", content=b"image=1", headers=headers)
    assert_problem(response, 415, "multipart/form-data", "application/json")


@pytest.mark.parametrize("text", ["@@not base64@@", "abc", "Zm9v!"])
def test_invalid_base64_is_422(limited_api: InProcess, instance: dict, text: str) -> None:
    response = limited_api.client.post("/v1/predict", json={"image_base64": text, "instances": [instance]})
    assert_problem(response, 422, "base64")


@pytest.mark.parametrize(
    ("data", "fragment"),
    [
        (b"GIF89a" + bytes(200), "gif"),
        (b"BM" + bytes(200), "bmp"),
        (b"hello, this is text and not an image", "jpeg or png"),
    ],
)
@pytest.mark.parametrize("form", ["json", "multipart"])
def test_not_a_jpeg_or_png_is_415(
    limited_api: InProcess, instance: dict, data: bytes, fragment: str, form: str
) -> None:
    send = predict_json if form == "json" else predict_multipart
    assert_problem(send(limited_api.client, data, {"instances": [instance]}), 415, fragment)


def test_corrupt_image_is_422(limited_api: InProcess, instance: dict, samples: list[Sample]) -> None:
    data = samples[0].image_path.read_bytes()
    response = predict_json(limited_api.client, data[: len(data) // 2], {"instances": [instance]})
    assert_problem(response, 422, "cannot be decoded")


def test_empty_image_is_422(limited_api: InProcess, instance: dict) -> None:
    response = predict_multipart(limited_api.client, b"", {"instances": [instance]})
    assert_problem(response, 422, "empty")


def test_image_over_the_pixel_limit_is_413(limited_api: InProcess, instance: dict, limits: dict) -> None:
    side = math.isqrt(limits["max_image_pixels"]) + 50
    response = predict_json(limited_api.client, png(side, side), {"instances": [instance]})
    assert_problem(response, 413, "CKS_MAX_IMAGE_PIXELS")


def test_pixel_limit_is_checked_from_the_header(limited_api: InProcess, instance: dict) -> None:
    """A 100000 x 100000 PNG header with no pixels: refused as too large, nothing decoded."""
    response = predict_multipart(
        limited_api.client, png_header_only(100_000, 100_000), {"instances": [instance]}
    )
    assert_problem(response, 413, "100000x100000", "CKS_MAX_IMAGE_PIXELS")


def test_body_over_the_request_limit_is_413(limited_api: InProcess, instance: dict, limits: dict) -> None:
    padding = bytes(limits["max_request_bytes"])
    response = predict_json(limited_api.client, padding, {"instances": [instance]})
    assert_problem(response, 413, "CKS_MAX_REQUEST_BYTES")
    response = predict_multipart(limited_api.client, padding, {"instances": [instance]})
    assert_problem(response, 413, "CKS_MAX_REQUEST_BYTES")


def test_streamed_body_over_the_request_limit_is_413(limited_api: InProcess, limits: dict) -> None:
    def chunks():
        yield b'{"instances": [], "image_base64": "'
        for _ in range(limits["max_request_bytes"] // 65536 + 2):
            yield b"A" * 65536
        yield b'"}'

    response = limited_api.client.post(
        "/v1/predict", content=chunks(), headers={"Content-Type": "application/json"}
    )
    assert_problem(response, 413, "CKS_MAX_REQUEST_BYTES")


def test_more_instances_than_the_limit_is_422(
    limited_api: InProcess, small_image: bytes, instance: dict, fixed_limits: dict
) -> None:
    instances = [instance] * (fixed_limits["MAX_INSTANCES"] + 1)
    response = predict_json(limited_api.client, small_image, {"instances": instances})
    assert_problem(response, 422, "4 instances in one request; the limit is 3")
    at_limit = predict_json(
        limited_api.client, small_image, {"instances": [instance] * fixed_limits["MAX_INSTANCES"]}
    )
    assert at_limit.status_code == 200, at_limit.text


def test_unknown_object_is_422(limited_api: InProcess, small_image: bytes, object_name: str) -> None:
    instances = [
        {"object": object_name, "bbox": [10, 10, 50, 50]},
        {"object": "unicorn", "bbox": [1, 1, 9, 9]},
    ]
    response = predict_json(limited_api.client, small_image, {"instances": instances})
    assert_problem(response, 422, "instances[1]", "'unicorn'", object_name)


@pytest.mark.parametrize(
    ("bbox", "fragment"),
    [
        ([SMALL[0] + 5, 10, 50, 50], "outside"),
        ([10, SMALL[1], 50, 50], "outside"),
        ([-100, -100, 50, 50], "outside"),
        ([10, 10, 0, 50], "at least 1 pixel"),
        ([10, 10, 50, -3], "at least 1 pixel"),
        ([10, 10, 0.5, 0.5], "at least 1 pixel"),
        ([10, 10, 1e-6, 1e-6], "at least 1 pixel"),
        ([0, 0, 1e7, 1e7], "outside"),
        ([-3, 10, 20, 20], "clip the box"),
        ([10, 10, 50], "bbox"),
        ([10, 10, 50, "wide"], "bbox"),
    ],
)
def test_bad_bbox_is_422(
    limited_api: InProcess, small_image: bytes, object_name: str, bbox: list, fragment: str
) -> None:
    response = predict_json(
        limited_api.client, small_image, {"instances": [{"object": object_name, "bbox": bbox}]}
    )
    assert_problem(response, 422, "bbox", fragment)


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity", "1e999"])
@pytest.mark.parametrize("form", ["json", "multipart"])
def test_non_finite_bbox_is_422(
    limited_api: InProcess, small_image: bytes, object_name: str, token: str, form: str
) -> None:
    instances = f'[{{"object": {json.dumps(object_name)}, "bbox": [10, 10, {token}, 40]}}]'
    if form == "json":
        text = f'{{"image_base64": "{b64(small_image)}", "instances": {instances}}}'
        response = raw_json_post(limited_api, text)
    else:
        files = {
            "image": ("image.png", small_image, "image/png"),
            "request": (None, f'{{"instances": {instances}}}', "application/json"),
        }
        response = limited_api.client.post("/v1/predict", files=files)
    assert_problem(response, 422, "bbox")


@pytest.mark.parametrize(
    "options",
    [
        {"epsilon": 0},
        {"epsilon": 1},
        {"epsilon": -0.1},
        {"epsilon": 1.5},
        {"delta": 0},
        {"delta": 1},
        {"nonconformity": "gaussian"},
        {"coverage": "image"},
        {"calibration_version": 0},
        {"calibration_version": 2**40},
        {"include_statistics": "perhaps"},
        {"unexpected_option": 1},
    ],
)
def test_bad_options_are_422(
    limited_api: InProcess, small_image: bytes, instance: dict, options: dict
) -> None:
    response = predict_json(limited_api.client, small_image, {"instances": [instance], **options})
    assert_problem(response, 422, next(iter(options)))


@pytest.mark.parametrize("epsilon", [1.5, 0, 1, -0.1, 90])
def test_an_epsilon_outside_0_1_is_told_what_epsilon_is(
    limited_api: InProcess, small_image: bytes, instance: dict, epsilon: float
) -> None:
    response = predict_json(limited_api.client, small_image, {"instances": [instance], "epsilon": epsilon})
    body = assert_problem(response, 422, f"epsilon: {epsilon} is not a probability")
    assert "the probability that a set misses its keypoint, between 0 and 1" in body["detail"], body


def test_epsilon_at_the_limits_of_the_open_interval_is_accepted(
    limited_api: InProcess, small_image: bytes, instance: dict
) -> None:
    for epsilon in (1e-9, 0.999999):
        response = predict_json(
            limited_api.client, small_image, {"instances": [instance], "epsilon": epsilon}
        )
        assert response.status_code == 200, response.text


def test_missing_calibration_version_is_404(
    limited_api: InProcess, small_image: bytes, instance: dict
) -> None:
    missing = max(limited_api.versions()) + 1000
    response = predict_json(
        limited_api.client, small_image, {"instances": [instance], "calibration_version": missing}
    )
    assert_problem(response, 404, str(missing))


@pytest.mark.parametrize("parameters", [{}, {"instances": []}, {"instances": [{"object": "x"}]}])
def test_missing_or_empty_instances_are_422(
    limited_api: InProcess, small_image: bytes, parameters: dict
) -> None:
    assert_problem(predict_json(limited_api.client, small_image, parameters), 422, "instances")


def test_json_body_that_is_not_json_is_422(limited_api: InProcess) -> None:
    assert_problem(raw_json_post(limited_api, '{"instances": [,'), 422)
    assert_problem(raw_json_post(limited_api, "[1, 2, 3]"), 422)


def test_a_request_part_in_single_quotes_names_the_part_and_double_quotes(
    limited_api: InProcess, small_image: bytes, instance: dict
) -> None:
    single_quoted = json.dumps({"instances": [instance]}).replace('"', "'")
    files = {"image": ("image.png", small_image, "image/png"), "request": (None, single_quoted)}
    body = assert_problem(limited_api.client.post("/v1/predict", files=files), 422)
    (error,) = body["errors"]
    assert error.startswith("the multipart part 'request' is not valid JSON (key must be a string at"), error
    assert "double quotes" in error, error


def test_multipart_without_its_parts_is_422(
    limited_api: InProcess, small_image: bytes, instance: dict
) -> None:
    only_request = {"request": (None, json.dumps({"instances": [instance]}), "application/json")}
    assert_problem(limited_api.client.post("/v1/predict", files=only_request), 422, "'image'")
    only_image = {"image": ("image.png", small_image, "image/png")}
    assert_problem(limited_api.client.post("/v1/predict", files=only_image), 422, "'request'")
    not_json = {**only_image, "request": (None, "instances=duck", "text/plain")}
    assert_problem(limited_api.client.post("/v1/predict", files=not_json), 422)
    garbage = limited_api.client.post(
        "/v1/predict",
        content=b"--xyz\r\nnot a part",
        headers={"Content-Type": "multipart/form-data; boundary=xyz"},
    )
    assert_problem(garbage, 422)


def test_unknown_routes_and_methods_are_problems(limited_api: InProcess) -> None:
    assert_problem(limited_api.client.get("/v1/nothing-here"), 404)
    assert_problem(limited_api.client.get("/v1/predict"), 405)
