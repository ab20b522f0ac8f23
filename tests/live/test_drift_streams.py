"""The drift alarm on a camera stream, through the service in process: 300 frames of one static
scene raise no alarm (one independent look), a stream of heavily occluded scenes raises it, and
/v1/admin/drift (what the console reads) says both, with the looks it counted.

Frames are rendered here by the bundled generator with seeds no bundled split used
(tests/streams.py): one scene filmed by a camera moving back and forth, then heavily occluded
scenes (3 extra occluders) of a few frames each, as a robot moving from table to table.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.api.in_process import InProcess
from tests.predict_client import predict_ok
from tests.service_calls import ADMIN_TOKEN, ServiceCalls
from tests.streams import RequestFrame, render_requests, render_scenes

STATIC_FRAMES = 300
#: heavy scenes sent, at most, and frames per scene (a still camera: the frame repeats)
HEAVY_SCENES, FRAMES_PER_SCENE = 150, 3


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[InProcess]:
    with InProcess(tmp_path_factory.mktemp("streams") / "data", admin_token=ADMIN_TOKEN) as service:
        yield service


def drift(server: ServiceCalls) -> dict:
    response = server.client.get("/v1/admin/drift", headers=server.admin)
    assert response.status_code == 200, response.text
    return response.json()


def send(server: ServiceCalls, frame: RequestFrame) -> None:
    image, instances = frame
    predict_ok(server.client, image, {"instances": instances})


def static_scene_stream() -> list[RequestFrame]:
    """One scene, a camera going back and forth over 6 rendered frames, 300 frames in all."""
    (views,) = render_requests(9401, 1, 6)
    back_and_forth = views + views[-2:0:-1]
    return [back_and_forth[k % len(back_and_forth)] for k in range(STATIC_FRAMES)]


def send_static_scene(server: ServiceCalls) -> dict:
    """300 frames of one scene; the drift document after them."""
    for frame in static_scene_stream():
        send(server, frame)
    return drift(server)


def send_heavy_until_alarm(server: ServiceCalls) -> tuple[int, dict]:
    """Heavily occluded scenes until the alarm (at most HEAVY_SCENES); how many, and the document."""
    sent = 0
    while sent < HEAVY_SCENES:
        for (frame,) in render_scenes(range(9402 + sent, 9402 + sent + 5), 1, "heavy_occlusion"):
            for _ in range(FRAMES_PER_SCENE):
                send(server, frame)
        sent += 5
        if drift(server)["alarm"]:
            break
    return sent, drift(server)


def test_a_static_scene_is_quiet_and_heavy_occlusion_alarms(server: ServiceCalls) -> None:
    quiet = send_static_scene(server)
    assert quiet["statistic"] == "sequential" and quiet["frames"] == STATIC_FRAMES
    assert quiet["independent_looks"] == 1 and not quiet["alarm"], quiet["evidence"]

    sent, shifted = send_heavy_until_alarm(server)
    assert shifted["alarm"], f"no alarm after {sent} heavily occluded scenes: evidence {shifted['evidence']}"
    assert shifted["frames"] == STATIC_FRAMES + FRAMES_PER_SCENE * sent
    # A scene's frames are one look, and scenes are cuts: a few scenes whose boxes look alike may
    # pass for one (36 looks for 40 scenes was seen), never a frame for a scene.
    assert 1 + 0.8 * sent <= shifted["independent_looks"] <= 1 + sent
    assert shifted["evidence"] >= shifted["evidence_threshold"] == 2 / shifted["alarm_threshold"]
    print(
        f"heavy occlusion: alarm after {sent} scenes ({FRAMES_PER_SCENE * sent} frames,"
        f" {shifted['independent_looks'] - 1} looks)"
    )
