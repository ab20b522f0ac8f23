"""POST /v1/predict/frame in process: a frame sent whole or as its boxes' regions, raw or PNG, gets
byte for byte the answer POST /v1/predict gives the whole image's pixels; every malformed frame,
region or raw body is a 4xx problem that says what to fix."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from service.detector.crop import crop_contexts
from service.detector.images import decode_image
from tests.api.in_process import InProcess
from tests.predict_client import instances_of
from tests.samples import Sample, model_dir, samples_by_image
from tests.service_calls import assert_problem

PADDING = json.loads((model_dir() / "manifest.json").read_text())["crop"]["padding"]
RAW = {"rgb8": lambda bgr: bgr[..., ::-1], "bgr8": lambda bgr: bgr, "mono8": lambda gray: gray}


def png(pixels: np.ndarray) -> bytes:
    return cv2.imencode(".png", pixels)[1].tobytes()


def encoded(pixels: np.ndarray, encoding: str) -> bytes:
    """``pixels`` (BGR or gray) as ``encoding``: a PNG file, or raw row-major bytes."""
    return png(pixels) if encoding == "png" else np.ascontiguousarray(RAW[encoding](pixels)).tobytes()


def whole_answer(api: InProcess, pixels: np.ndarray, parameters: dict) -> bytes:
    files = {"image": ("frame.png", png(pixels), "image/png")}
    response = api.client.post("/v1/predict", files=files, data={"request": json.dumps(parameters)})
    assert response.status_code == 200, response.text
    return response.content


def post_frame(api: InProcess, request: dict, pixels: Sequence[bytes]) -> Any:
    files: list[tuple[str, tuple[str | None, bytes, str]]] = [
        ("request", (None, json.dumps(request).encode(), "application/json"))
    ]
    files += [("pixels", ("pixels", data, "application/octet-stream")) for data in pixels]
    return api.client.post("/v1/predict/frame", files=files)


def regions_request(
    pixels: np.ndarray, parameters: dict, encoding: str, groups: Sequence[Sequence[int]] | None = None
) -> tuple[dict, list[bytes]]:
    """One region per group of instances (default: per instance), each the bounding rectangle of
    its instances' crop contexts."""
    height, width = pixels.shape[:2]
    boxes = [instance["bbox"] for instance in parameters["instances"]]
    contexts = crop_contexts(np.array(boxes), PADDING, width, height)
    regions, parts = [], []
    for group in groups or [[i] for i in range(len(boxes))]:
        x0, y0 = contexts[list(group), :2].min(axis=0)
        x1, y1 = contexts[list(group), 2:].max(axis=0)
        rectangle = {"x_offset": int(x0), "y_offset": int(y0), "width": int(x1 - x0), "height": int(y1 - y0)}
        regions.append({**rectangle, "encoding": encoding, "instances": list(group)})
        parts.append(encoded(pixels[y0:y1, x0:x1], encoding))
    return {**parameters, "frame": {"width": width, "height": height}, "regions": regions}, parts


def whole_request(pixels: np.ndarray, parameters: dict, encoding: str) -> tuple[dict, list[bytes]]:
    frame = {"width": pixels.shape[1], "height": pixels.shape[0], "encoding": encoding}
    return {**parameters, "frame": frame}, [encoded(pixels, encoding)]


@pytest.fixture(scope="module")
def frames(samples: list[Sample]) -> list[tuple[np.ndarray, dict]]:
    """Each bundled sample image decoded as the service decodes it, with its labeled instances."""
    return [
        (decode_image(path.read_bytes(), 10**8), {"instances": instances_of(group)})
        for path, group in samples_by_image(samples).items()
    ]


@pytest.fixture(scope="module")
def full_hd(frames: list[tuple[np.ndarray, dict]]) -> tuple[np.ndarray, dict]:
    """A 1920x1080 frame: the first sample scaled x2 at (500, 60), the second as it is in the
    bottom-right corner, and boxes in the frame's corners, whose crop contexts the edges clip."""
    (first, first_parameters), (second, second_parameters) = frames[0], frames[1]
    canvas = np.full((1080, 1920, 3), 40, dtype=np.uint8)
    canvas[60:1020, 500:1780] = cv2.resize(first, (1280, 960), interpolation=cv2.INTER_LINEAR)
    canvas[1080 - 480 :, 1920 - 640 :] = second
    instances = [
        {**i, "bbox": [500 + 2 * i["bbox"][0], 60 + 2 * i["bbox"][1], 2 * i["bbox"][2], 2 * i["bbox"][3]]}
        for i in first_parameters["instances"]
    ]
    instances += [
        {**i, "bbox": [1280 + i["bbox"][0], 600 + i["bbox"][1], *i["bbox"][2:]]}
        for i in second_parameters["instances"]
    ]
    corners = [[0.0, 0.0, 30.0, 50.0], [1880.5, 1040.0, 39.5, 40.0]]  # crop contexts clipped on every side
    instances += [{"object": instances[0]["object"], "bbox": bbox} for bbox in corners]
    return canvas, {"instances": instances}


def test_regions_and_whole_frames_raw_or_png_answer_the_whole_images_bytes(
    api: InProcess, frames: list[tuple[np.ndarray, dict]]
) -> None:
    for pixels, parameters in frames:
        expected = whole_answer(api, pixels, parameters)
        for request, parts in (
            regions_request(pixels, parameters, "rgb8"),
            regions_request(pixels, parameters, "bgr8", groups=[range(len(parameters["instances"]))]),
            regions_request(pixels, parameters, "png"),
            whole_request(pixels, parameters, "bgr8"),
            whole_request(pixels, parameters, "rgb8"),
            whole_request(pixels, parameters, "png"),
        ):
            response = post_frame(api, request, parts)
            assert response.status_code == 200, response.text
            assert response.content == expected, request.get("regions", request["frame"])


def test_a_whole_jpeg_decoded_in_a_window_answers_as_its_full_decode(
    api: InProcess, frames: list[tuple[np.ndarray, dict]], full_hd: tuple[np.ndarray, dict]
) -> None:
    """POST /v1/predict and /frame decode a whole JPEG only around its boxes
    (service/detector/native/jpeg_window.c): the answer is its fully decoded pixels' (as PNG)."""
    for pixels, parameters in [*frames, full_hd]:
        jpeg = cv2.imencode(".jpg", pixels, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
        expected = whole_answer(api, decode_image(jpeg, 10**8), parameters)
        files = {"image": ("frame.jpg", jpeg, "image/jpeg")}
        response = api.client.post("/v1/predict", files=files, data={"request": json.dumps(parameters)})
        assert response.status_code == 200 and response.content == expected
        height, width = pixels.shape[:2]
        request = {**parameters, "frame": {"width": width, "height": height, "encoding": "jpeg"}}
        response = post_frame(api, request, [jpeg])
        assert response.status_code == 200 and response.content == expected


def test_a_1080p_frame_with_boxes_at_its_edges_answers_the_same_bytes(
    api: InProcess, full_hd: tuple[np.ndarray, dict]
) -> None:
    pixels, parameters = full_hd
    # every heatmap statistic (what drift records and retention keep) and the difficulty strata
    parameters = {**parameters, "include_statistics": True, "stratify": "difficulty", "epsilon": 0.2}
    expected = whole_answer(api, pixels, parameters)
    assert b'"stratum"' in expected and b'"statistics"' in expected
    contexts = crop_contexts(np.array([i["bbox"] for i in parameters["instances"]]), PADDING, 1920, 1080)
    assert contexts[:, :2].min() == 0 and tuple(contexts[:, 2:].max(axis=0)) == (1920, 1080)
    for request, parts in (
        regions_request(pixels, parameters, "rgb8"),
        regions_request(pixels, parameters, "png"),
        whole_request(pixels, parameters, "rgb8"),
    ):
        assert post_frame(api, request, parts).content == expected


def test_gray_frames_as_mono8_regions_answer_as_the_gray_png(
    api: InProcess, frames: list[tuple[np.ndarray, dict]]
) -> None:
    pixels, parameters = frames[2]
    gray = cv2.cvtColor(pixels, cv2.COLOR_BGR2GRAY)
    expected = whole_answer(api, gray, parameters)
    for request, parts in (
        regions_request(gray, parameters, "mono8"),
        whole_request(gray, parameters, "mono8"),
    ):
        assert post_frame(api, request, parts).content == expected


def test_pose_sets_from_regions_are_the_whole_frames(api: InProcess, samples: list[Sample]) -> None:
    path, group = next(iter(samples_by_image(samples).items()))
    pixels = decode_image(path.read_bytes(), 10**8)
    sample = next(s for s in group)
    camera = [[572.0, 0.0, 320.0], [0.0, 572.0, 240.0], [0.0, 0.0, 1.0]]
    parameters = {
        "instances": instances_of([sample]),
        "coverage": "object",
        "pose": {"K": camera, "samples": 20, "outer_programs": 10},
    }
    expected = whole_answer(api, pixels, parameters)
    assert b'"pose"' in expected
    assert post_frame(api, *regions_request(pixels, parameters, "rgb8")).content == expected


# ---------------------------------------------------------------- refusals


@pytest.fixture(scope="module")
def frame(frames: list[tuple[np.ndarray, dict]]) -> tuple[np.ndarray, dict]:
    return frames[0]


def _with_region(request: dict, index: int, **changes: Any) -> dict:
    regions = [dict(region) for region in request["regions"]]
    regions[index].update(changes)
    return {**request, "regions": regions}


def test_raw_bytes_that_disagree_with_the_shape_are_told_the_expected_count(api: InProcess, frame) -> None:
    pixels, parameters = frame
    request, parts = regions_request(pixels, parameters, "rgb8")
    region = request["regions"][0]
    expected = region["width"] * region["height"] * 3
    assert_problem(post_frame(api, request, [parts[0][:-1], *parts[1:]]), 422, f"needs {expected} bytes")
    whole, data = whole_request(pixels, parameters, "mono8")
    assert_problem(post_frame(api, whole, data), 422, f"needs {640 * 480} bytes")


def test_a_region_outside_the_frame_is_refused(api: InProcess, frame) -> None:
    pixels, parameters = frame
    request, parts = regions_request(pixels, parameters, "rgb8")
    outside = _with_region(request, 0, x_offset=640 - request["regions"][0]["width"] + 5)
    assert_problem(
        post_frame(api, outside, parts), 422, "outside the 640x480 frame", "x_offset + width <= 640"
    )


def test_a_region_missing_a_margin_is_told_which_and_by_how_many_pixels(api: InProcess, frame) -> None:
    pixels, parameters = frame
    request, _ = regions_request(pixels, parameters, "rgb8")
    region = request["regions"][0]
    x, y, width, height = region["x_offset"], region["y_offset"], region["width"], region["height"]
    cut = {"x_offset": x + 3, "y_offset": y, "width": width - 3, "height": height - 2}
    parts = [encoded(pixels[y : y + height - 2, x + 3 : x + width], "rgb8")]
    narrow = {**request, "regions": [{**region, **cut}]}
    narrow["instances"] = parameters["instances"][:1]
    assert_problem(
        post_frame(api, narrow, parts), 422, "3 px on the left", "2 px on the bottom", "crop context"
    )


def test_unknown_encodings_and_instances_no_region_serves_are_refused(api: InProcess, frame) -> None:
    pixels, parameters = frame
    request, parts = regions_request(pixels, parameters, "rgb8")
    assert_problem(post_frame(api, _with_region(request, 0, encoding="rgba8"), parts), 422, "encoding")
    unserved = {**request, "regions": request["regions"][:1]}
    assert_problem(post_frame(api, unserved, parts[:1]), 422, "no region serves instances[1]")
    twice = _with_region(request, 1, instances=[0, 1])
    assert_problem(post_frame(api, twice, parts), 422, "all serve instances[0]")
    beyond = _with_region(request, 1, instances=[1, 7])
    assert_problem(post_frame(api, beyond, parts), 422, "names instance 7")


def test_parts_that_do_not_match_the_request_are_refused(api: InProcess, frame) -> None:
    pixels, parameters = frame
    request, parts = regions_request(pixels, parameters, "rgb8")
    assert_problem(post_frame(api, request, parts[:1]), 422, "1 'pixels' parts", f"send {len(parts)}")
    both = {**request, "frame": {**request["frame"], "encoding": "rgb8"}}
    assert_problem(post_frame(api, both, parts), 422, "either frame.encoding")
    as_png = _with_region(request, 0, encoding="png")
    assert_problem(post_frame(api, as_png, parts), 415, "JPEG or PNG")
    png_parts = regions_request(pixels, parameters, "png")[1]
    wrong_size = _with_region(request, 0, encoding="png", width=request["regions"][0]["width"] - 1)
    assert_problem(post_frame(api, wrong_size, png_parts), 422, "a region's width and height are its image's")
    jpeg = cv2.imencode(".jpg", pixels)[1].tobytes()
    whole = {**parameters, "frame": {"width": 640, "height": 480, "encoding": "png"}}
    assert_problem(post_frame(api, whole, [jpeg]), 422, "png but its bytes are a JPEG")
    response = api.client.post("/v1/predict/frame", json=request)
    assert_problem(response, 415, "multipart/form-data")
    files = [("request", (None, b"{", "application/json")), ("pixels", ("p", parts[0], "x"))]
    assert_problem(api.client.post("/v1/predict/frame", files=files), 422, "schema")
    extra = [
        ("request", (None, json.dumps(request).encode(), "application/json")),
        ("image", ("p", b"x", "x")),
    ]
    assert_problem(api.client.post("/v1/predict/frame", files=extra), 422, "'pixels' per region")


def test_mixed_gray_and_colour_regions_are_refused(api: InProcess, frame) -> None:
    pixels, parameters = frame
    request, parts = regions_request(pixels, parameters, "rgb8")
    region = request["regions"][1]
    gray = cv2.cvtColor(pixels, cv2.COLOR_BGR2GRAY)
    y, x = region["y_offset"], region["x_offset"]
    mono = encoded(gray[y : y + region["height"], x : x + region["width"]], "mono8")
    mixed = _with_region(request, 1, encoding="mono8")
    assert_problem(post_frame(api, mixed, [parts[0], mono, *parts[2:]]), 422, "mix gray and colour")


def test_frames_above_the_pixel_and_memory_limits_are_refused_before_decoding(tmp_path: Path, frames) -> None:
    pixels, parameters = frames[0]
    with InProcess(tmp_path / "data", {"MAX_DECODED_BYTES": 30_000}, max_image_pixels=640 * 479) as small:
        whole, data = whole_request(pixels, parameters, "bgr8")
        assert_problem(post_frame(small, whole, data), 413, "640x480 = 307200 pixels", "CKS_MAX_IMAGE_PIXELS")
        tall = {**whole, "frame": {"width": 640, "height": 2**31 - 1, "encoding": "bgr8"}}
        assert_problem(post_frame(small, tall, data), 413, "CKS_MAX_IMAGE_PIXELS")
        crop = pixels[:400]
        request, parts = regions_request(crop, parameters, "rgb8")
        assert_problem(post_frame(small, request, parts), 413, "above the limit of 30000 bytes")


def test_a_frame_sent_as_regions_can_be_retained_for_feedback(api: InProcess, frame) -> None:
    pixels, parameters = frame
    request, parts = regions_request(pixels, {**parameters, "retain": True}, "rgb8")
    response = post_frame(api, request, parts)
    assert response.status_code == 200, response.text
    answer = response.json()
    assert answer["prediction_id"]
    plain = post_frame(api, regions_request(pixels, parameters, "rgb8")[0], parts).json()
    assert {k: v for k, v in answer.items() if k != "prediction_id"} == plain
