"""The client's numpy frames against a real server: sent as their boxes' regions (raw or PNG) or
whole and raw, they get the answer the PNG of the same frame gets; as JPEG regions, an answer."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator

import cv2
import numpy as np
import pytest
from keypoint_client import AsyncKeypointClient, InvalidInput, KeypointClient, png_bytes
from keypoint_client.frames import crop_context, frame_parts

from service.detector.crop import crop_contexts
from tests.live.server import LiveServer
from tests.predict_client import instances_of
from tests.samples import Sample, model_dir, samples_by_image


@pytest.fixture(scope="module")
def client(server: LiveServer) -> Iterator[KeypointClient]:
    with KeypointClient(server.url) as client:
        yield client


@pytest.fixture(scope="module")
def frames(samples: list[Sample]) -> list[tuple[np.ndarray, list[dict]]]:
    """Three sample frames as RGB arrays, with their instances."""
    groups = list(samples_by_image(samples).items())[:3]
    return [(cv2.imread(str(path))[:, :, ::-1].copy(), instances_of(group)) for path, group in groups]


def test_a_numpy_frame_gets_the_answer_of_the_png_of_its_pixels(client: KeypointClient, frames) -> None:
    for rgb, instances in frames:
        expected = client.predict(png_bytes(rgb), instances, epsilon=0.2)
        for sending in ("regions", "png-regions", "raw-frame"):
            assert client.predict(rgb, instances, epsilon=0.2, frame_sending=sending) == expected, sending
        bgr = np.ascontiguousarray(rgb[:, :, ::-1])
        assert client.predict(bgr, instances, epsilon=0.2, channel_order="bgr") == expected
        lossy = client.predict(rgb, instances, epsilon=0.2, frame_sending="jpeg-regions")
        assert [len(i.keypoints) for i in lossy.instances] == [len(i.keypoints) for i in expected.instances]
    gray = np.ascontiguousarray(frames[0][0][:, :, 1])
    assert client.predict(gray, frames[0][1]) == client.predict(png_bytes(gray), frames[0][1])
    assert client.predict(gray[:, :, None], frames[0][1]) == client.predict(png_bytes(gray), frames[0][1])


def test_the_async_client_sends_frames_too(server: LiveServer, frames) -> None:
    rgb, instances = frames[0]

    async def both() -> tuple:
        async with AsyncKeypointClient(server.url) as client:
            return await client.predict(rgb, instances), await client.predict(png_bytes(rgb), instances)

    from_frame, from_png = asyncio.run(both())
    assert from_frame == from_png


def test_the_clients_crop_context_is_the_services() -> None:
    padding = float(json.loads((model_dir() / "manifest.json").read_text())["crop"]["padding"])
    rng = np.random.default_rng(0)
    boxes = np.column_stack([rng.uniform(-1, 600, (200, 2)), rng.uniform(1, 400, (200, 2))])
    service = crop_contexts(boxes, padding, 640, 480)
    assert [crop_context(box, padding, 640, 480) for box in boxes] == [
        tuple(map(int, row)) for row in service
    ]


def test_boxes_whose_contexts_overlap_share_a_region(client: KeypointClient, frames) -> None:
    rgb, instances = frames[0]
    twice = [instances[0], instances[0], *instances[1:]]
    request = json.loads(frame_parts(rgb, {"instances": twice}, 0.25)[0][1][1])
    served = [region["instances"] for region in request["regions"]]
    assert served[0] == [0, 1] and sorted(i for group in served for i in group) == list(range(len(twice)))
    assert client.predict(rgb, twice) == client.predict(png_bytes(rgb), twice)


def test_a_box_outside_the_frame_is_the_services_problem(client: KeypointClient, frames) -> None:
    rgb, _ = frames[0]
    with pytest.raises(InvalidInput, match="outside the 640x480 image"):
        client.predict(rgb, [("duck", [700.0, 500.0, 20.0, 20.0])])
