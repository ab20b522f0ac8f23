"""The client's predictions against a real server: typed results that mirror the API's JSON,
set geometry, numpy images, typed problems, the drawn PNG, many images per call, asyncio."""

from __future__ import annotations

import asyncio
import re
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from keypoint_client import (
    AsyncKeypointClient,
    Ball,
    Ellipse,
    InvalidInput,
    KeypointClient,
    NotFound,
    PredictRequest,
    PredictResult,
    ProblemError,
    Unbounded,
    UnsupportedMediaType,
    png_bytes,
)

from service.detector.images import decode_image
from tests.live.server import LiveServer
from tests.predict_client import instances_of, predict_json
from tests.samples import Sample, samples_by_image

SET_TYPES = {"peak": Ball, "var": Ball, "cov": Ellipse}
OPTIONS = ("epsilon", "nonconformity", "coverage", "delta", "calibration_version", "include_statistics")


@pytest.fixture(scope="module")
def client(server: LiveServer) -> Iterator[KeypointClient]:
    with KeypointClient(server.url) as client:
        yield client


@pytest.fixture(scope="module")
def images(samples: list[Sample]) -> list[tuple[Path, list[dict]]]:
    return [(path, instances_of(group)) for path, group in samples_by_image(samples).items()]


def polygon_area(outline: np.ndarray) -> float:
    x, y = outline[:, 0], outline[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1))))


@pytest.mark.parametrize("function", ["peak", "var", "cov"])
def test_results_are_typed_and_mirror_the_json(
    server: LiveServer, client: KeypointClient, images, function: str
) -> None:
    for path, instances in images:
        result = client.predict(path, instances, nonconformity=function, epsilon=0.1)
        parameters = {"instances": instances, "nonconformity": function, "epsilon": 0.1}
        assert result.to_dict() == predict_json(server.client, path.read_bytes(), parameters).json()
        for keypoint in (k for instance in result.instances for k in instance.keypoints):
            region, guarantee = keypoint.set, keypoint.guarantee
            assert isinstance(region, SET_TYPES[function]) and region.center == keypoint.point
            assert guarantee.bounded and guarantee.coverage_lower_bound == pytest.approx(0.9)
            assert guarantee.conditional_coverage.a == guarantee.n + 1 - guarantee.t
            center = np.asarray(region.center)
            outline = region.boundary(720)
            assert outline.shape == (720, 2)
            assert region.contains(center + 0.999 * (outline - center)).all()
            assert not region.contains(center + 1.001 * (outline - center)).any()
            assert polygon_area(outline) == pytest.approx(region.area, rel=1e-4)


def test_too_small_an_epsilon_gives_the_whole_plane(client: KeypointClient, images) -> None:
    path, instances = images[0]
    result = client.predict(path, instances, epsilon=1e-5)  # n of thousands: t = floor((n + 1) * 1e-5) = 0
    keypoint = result.instances[0].keypoints[0]
    assert isinstance(keypoint.set, Unbounded) and not keypoint.guarantee.bounded
    assert keypoint.set.area == float("inf") and keypoint.set.boundary().shape == (0, 2)
    far = np.array([[-1e9, 1e9], [keypoint.point[0], keypoint.point[1]]])
    assert keypoint.set.contains(far).tolist() == [True, True]
    assert keypoint.set.contains((0.0, 0.0)).shape == ()


def as_opencv_reads_it(pixels: np.ndarray) -> np.ndarray:
    """What OpenCV's imdecode(IMREAD_UNCHANGED) makes of a PNG of these RGB-ordered pixels."""
    if pixels.ndim == 2:
        return pixels
    if pixels.shape[2] == 2:  # gray + alpha comes back as BGRA
        gray, alpha = pixels[:, :, 0], pixels[:, :, 1]
        return np.stack([gray, gray, gray, alpha], axis=2)
    return np.concatenate([pixels[:, :, 2::-1], pixels[:, :, 3:]], axis=2)


def test_numpy_images_are_sent_as_lossless_png(client: KeypointClient, images) -> None:
    path, instances = images[0]
    from_file = client.predict(path, instances).to_dict()
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert client.predict(bgr, instances, channel_order="bgr").to_dict() == from_file
    assert client.predict(bgr[:, :, ::-1], instances).to_dict() == from_file  # RGB, the default order

    rng = np.random.default_rng(0)
    for pixels in (
        rng.integers(0, 256, (5, 7), dtype=np.uint8),
        rng.integers(0, 256, (5, 7, 2), dtype=np.uint8),
        rng.integers(0, 256, (5, 7, 4), dtype=np.uint8),
        rng.integers(0, 65536, (5, 7, 3), dtype=np.uint16),
    ):
        data = png_bytes(pixels)
        decode_image(data, 100)  # the service's strict decoder accepts it
        stored = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        assert np.array_equal(stored, as_opencv_reads_it(pixels)), pixels.shape
    with pytest.raises(ValueError, match="uint8 or uint16"):
        png_bytes(np.zeros((4, 4), dtype=np.float32))
    with pytest.raises(ValueError, match=r"\(H, W\) or \(H, W, C\)"):
        png_bytes(np.zeros((4, 4, 5), dtype=np.uint8))


def test_problems_are_typed_exceptions(client: KeypointClient, images) -> None:
    path, instances = images[0]
    with pytest.raises(InvalidInput) as invalid:
        client.predict(path, [("no-such-object", [10, 10, 20, 20])])
    error = invalid.value
    assert error.status == 422 and "is not an object of model" in error.detail
    assert any("no-such-object" in line for line in error.errors)
    assert re.fullmatch(r"[0-9a-f]{32}", error.request_id or ""), error.request_id
    assert error.body["status"] == 422 and str(error).startswith("422 ")

    with pytest.raises(UnsupportedMediaType) as unsupported:
        client.predict(b"GIF89a, not a JPEG", instances)
    assert unsupported.value.status == 415 and "JPEG or PNG" in unsupported.value.detail
    with pytest.raises(NotFound) as missing:
        client.predict(path, instances, calibration_version=99)
    assert missing.value.status == 404 and "99" in missing.value.detail
    assert isinstance(missing.value, ProblemError)


def test_the_png_is_the_services_drawing(server: LiveServer, client: KeypointClient, images) -> None:
    path, instances = images[1]
    drawn = client.predict_png(path, instances, nonconformity="var")
    parameters = {"instances": instances, "nonconformity": "var"}
    direct = predict_json(server.client, path.read_bytes(), parameters, headers={"Accept": "image/png"})
    assert drawn.startswith(b"\x89PNG") and drawn == direct.content


def batch_requests(images) -> list[PredictRequest]:
    """Good and bad images mixed: a bad one in front, in the middle and at the end."""
    (first, first_instances), (second, second_instances), (third, third_instances) = images[:3]
    return [
        PredictRequest(b"not an image", first_instances),
        PredictRequest(first, first_instances),
        PredictRequest(second, second_instances, nonconformity="peak", epsilon=0.2),
        PredictRequest(third, [("no-such-object", [1, 1, 9, 9])]),
        PredictRequest(third, third_instances, coverage="object", delta=0.1, include_statistics=True),
        PredictRequest(first, first_instances, calibration_version=99),
    ]


def expected_answers(client: KeypointClient, requests: list[PredictRequest]) -> list[object]:
    """What one predict per image answers: a result's JSON, or the error's type and detail."""
    answers: list[object] = []
    for request in requests:
        try:
            options = {name: getattr(request, name) for name in OPTIONS}
            answers.append(client.predict(request.image, request.instances, **options).to_dict())
        except ProblemError as error:
            answers.append((type(error), error.status, error.detail))
    return answers


def comparable(answers: list[PredictResult | ProblemError]) -> list[object]:
    return [
        answer.to_dict()
        if isinstance(answer, PredictResult)
        else (type(answer), answer.status, answer.detail)
        for answer in answers
    ]


def test_predict_many_answers_each_image_in_order(client: KeypointClient, images) -> None:
    requests = batch_requests(images)
    expected = expected_answers(client, requests)
    assert [type(a) if isinstance(a, tuple) else dict for a in expected] == [
        tuple,
        dict,
        dict,
        tuple,
        dict,
        tuple,
    ]
    assert comparable(client.predict_many(requests)) == expected
    assert comparable(client.predict_many(requests, batch_size=4)) == expected  # two requests


def test_the_asyncio_client_gives_the_same_answers(
    server: LiveServer, client: KeypointClient, images
) -> None:
    requests = batch_requests(images)
    path, instances = images[0]

    async def ask() -> tuple[PredictResult, list[PredictResult | ProblemError], list[PredictResult]]:
        async with AsyncKeypointClient(server.url) as asynchronous:
            alone = await asynchronous.predict(path, instances, nonconformity="var")
            many = await asynchronous.predict_many(requests, batch_size=5)
            concurrent = await asyncio.gather(*(asynchronous.predict(p, i) for p, i in images[:4]))
            return alone, many, list(concurrent)

    alone, many, concurrent = asyncio.run(ask())
    assert alone.to_dict() == client.predict(path, instances, nonconformity="var").to_dict()
    assert comparable(many) == comparable(client.predict_many(requests))
    assert [r.to_dict() for r in concurrent] == [client.predict(p, i).to_dict() for p, i in images[:4]]
