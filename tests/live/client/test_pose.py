"""Pose sets (PURSE) through the client, against a real server: the pose option typed (a camera
matrix from numpy, the intrinsics, checks of the samples' true poses), the answer's pose blocks
mirroring the API's JSON, the drawn PNG, batches and asyncio, refusals as typed exceptions."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from keypoint_client import (
    AsyncKeypointClient,
    InvalidInput,
    KeypointClient,
    OuterBound,
    Pose,
    PoseCheck,
    PoseRequest,
    PredictRequest,
    PredictResult,
    SampledBound,
)
from pydantic import ValidationError

from tests.live.server import LiveServer
from tests.predict_client import predict_json


@pytest.fixture(scope="module")
def client(server: LiveServer) -> Iterator[KeypointClient]:
    with KeypointClient(server.url) as client:
        yield client


@pytest.fixture(scope="module")
def scene(coco: dict, samples_dir: Path) -> tuple[Path, list[dict], list[str]]:
    """The first sample image, its annotations (true poses, camera) and their object names."""
    image = coco["images"][0]
    annotations = [a for a in coco["annotations"] if a["image_id"] == image["id"]]
    categories = {c["id"]: c["name"] for c in coco["categories"]}
    return samples_dir / image["file_name"], annotations, [categories[a["category_id"]] for a in annotations]


def instances(annotations: list[dict], names: list[str]) -> list[tuple[str, list[float]]]:
    return [(name, a["bbox"]) for a, name in zip(annotations, names, strict=True)]


def true_poses(annotations: list[dict]) -> list[PoseCheck]:
    """The samples' true poses, as numpy arrays: the client takes them as they are."""
    return [
        PoseCheck(instance=i, rotation=np.array(a["cam_R_m2c"]), translation=np.array(a["cam_t_m2c"]))
        for i, a in enumerate(annotations)
    ]


def pose_json(annotations: list[dict], **options: object) -> dict:
    """The same pose request as the API's JSON, written by hand."""
    checks = [
        {"instance": i, "rotation": a["cam_R_m2c"], "translation": a["cam_t_m2c"]}
        for i, a in enumerate(annotations)
    ]
    return {"K": annotations[0]["cam_K"], "check": checks, **options}


def test_pose_blocks_are_typed_and_mirror_the_json(server: LiveServer, client: KeypointClient, scene) -> None:
    path, annotations, names = scene
    camera = np.array(annotations[0]["cam_K"])
    pose = PoseRequest(K=camera, samples=20, check=true_poses(annotations))
    result = client.predict(path, instances(annotations, names), coverage="object", epsilon=0.1, pose=pose)

    boxes = [{"object": name, "bbox": bbox} for name, bbox in instances(annotations, names)]
    parameters = {
        "instances": boxes,
        "coverage": "object",
        "epsilon": 0.1,
        "pose": pose_json(annotations, samples=20),
    }
    answer = predict_json(server.client, path.read_bytes(), parameters)
    assert answer.status_code == 200, answer.text
    assert result.to_dict() == answer.json()
    assert PredictResult.model_validate_json(answer.content) == result

    for instance, annotation in zip(result.instances, annotations, strict=True):
        assert isinstance(instance.pose, Pose)
        estimate = instance.pose
        (check,) = estimate.checks  # its own true pose, tested for membership
        assert check.translation == pytest.approx(annotation["cam_t_m2c"])
        assert check.inside == all(v is not None and v <= 1 for v in check.violations)
        if estimate.empty:  # the sets missed (probability <= epsilon): nothing estimated
            assert estimate.rotation is None and estimate.method == "none"
            continue
        assert estimate.rotation is not None and estimate.translation is not None
        rotation = np.array(estimate.rotation)
        assert np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-9)
        assert estimate.largest_violation is not None and estimate.largest_violation <= 1.0
        assert isinstance(estimate.inner_bound, SampledBound) and estimate.inner_bound.poses_tried == 20
        assert isinstance(estimate.outer_bound, OuterBound)


def test_the_intrinsics_make_the_same_request(client: KeypointClient, scene) -> None:
    path, annotations, names = scene
    (fx, _, cx), (_, fy, cy), _ = annotations[0]["cam_K"]
    pinhole = PoseRequest.pinhole(fx, fy, cx, cy, samples=0, outer_bound=False)
    assert pinhole == PoseRequest(K=annotations[0]["cam_K"], samples=0, outer_bound=False)
    boxes = instances(annotations, names)
    with_pose = client.predict(path, boxes, coverage="object", pose=pinhole)
    without = client.predict(path, boxes, coverage="object")
    assert all(
        i.pose is not None and i.pose.inner_bound is None and i.pose.outer_bound is None
        for i in with_pose.instances
    )
    # The sets do not depend on the pose option; an answer without pose has no pose key.
    assert [i.keypoints for i in with_pose.instances] == [i.keypoints for i in without.instances]
    assert all(i.pose is None and "pose" not in i.to_dict() for i in without.instances)


def test_the_png_draws_the_pose(client: KeypointClient, scene) -> None:
    path, annotations, names = scene
    boxes, pose = instances(annotations, names), PoseRequest(K=annotations[0]["cam_K"], samples=0)
    drawn = client.predict_png(path, boxes, coverage="object", pose=pose)
    plain = client.predict_png(path, boxes, coverage="object")
    assert drawn.startswith(b"\x89PNG") and plain.startswith(b"\x89PNG") and drawn != plain


def test_pose_in_batches_and_with_asyncio(server: LiveServer, client: KeypointClient, scene) -> None:
    path, annotations, names = scene
    boxes, pose = instances(annotations, names), PoseRequest(K=annotations[0]["cam_K"], samples=5)
    single = client.predict(path, boxes, coverage="object", pose=pose)
    requests = [
        PredictRequest(path, boxes, coverage="object", pose=pose),
        PredictRequest(path, boxes, pose=pose),  # keypoint coverage: refused, that image alone
    ]
    batched, refused = client.predict_many(requests)
    assert batched == single
    assert isinstance(refused, InvalidInput) and "coverage" in refused.detail

    async def predict() -> PredictResult:
        async with AsyncKeypointClient(server.url) as asynchronous:
            return await asynchronous.predict(path, boxes, coverage="object", pose=pose)

    assert asyncio.run(predict()) == single


def test_refusals_are_typed(client: KeypointClient, scene) -> None:
    path, annotations, names = scene
    boxes, camera = instances(annotations, names), annotations[0]["cam_K"]
    with pytest.raises(InvalidInput, match="coverage") as keypoint_scope:
        client.predict(path, boxes, pose=PoseRequest(K=camera))
    assert keypoint_scope.value.status == 422
    skewed = [[camera[0][0], 3.0, camera[0][2]], camera[1], camera[2]]
    with pytest.raises(InvalidInput, match="pose.K"):
        client.predict(path, boxes, coverage="object", pose=PoseRequest(K=skewed))
    outside = PoseCheck(instance=len(boxes), rotation=np.eye(3), translation=(0.0, 0.0, 800.0))
    with pytest.raises(InvalidInput, match="pose.check"):
        client.predict(path, boxes, coverage="object", pose=PoseRequest(K=camera, check=[outside]))
    with pytest.raises(ValidationError, match="outer_programs"):  # the document's bounds, checked here
        PoseRequest(K=camera, outer_programs=2001)
