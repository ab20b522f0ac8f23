"""Pose sets (PURSE) through the ASGI app, on the bundled samples' true poses.

The samples carry each object's camera matrix and true pose, and their keypoint labels are the
exact projections of the manifest's 3D keypoints: so the true pose is in PURSE exactly when the
object-scope sets cover all of its keypoints, an event of probability >= 1 - epsilon.
"""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import betabinom

from tests.api.in_process import InProcess
from tests.predict_client import contains, predict_json, predict_ok
from tests.samples import b64
from tests.service_calls import ADMIN_TOKEN, assert_problem

EPSILONS = (0.1, 0.3)  # 0.3: smaller sets, more misses, more refining
BAND_ALPHA = 1e-3  # each tail of the coverage band


@dataclass(frozen=True)
class Case:
    epsilon: float
    camera: np.ndarray
    keypoints_3d: np.ndarray
    rotation: np.ndarray  # the true pose
    translation: np.ndarray
    answer: dict  # the response's instance


def project(camera: np.ndarray, rotation, translation, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(image points (N, 2), depths (N,)) of model points under a pose."""
    camera_points = points @ np.asarray(rotation).T + np.asarray(translation)
    homogeneous = camera_points @ camera.T
    return homogeneous[:, :2] / homogeneous[:, 2:3], camera_points[:, 2]


def in_sets(case: Case, rotation, translation) -> bool:
    points, depths = project(case.camera, rotation, translation, case.keypoints_3d)
    sets = [kp["set"] for kp in case.answer["keypoints"]]
    return bool((depths > 0).all()) and all(contains(s, tuple(p)) for s, p in zip(sets, points, strict=True))


def geodesic_deg(a, b) -> float:
    cosine = (float(np.trace(np.asarray(a).T @ np.asarray(b))) - 1) / 2
    return math.degrees(math.acos(min(1.0, max(-1.0, cosine))))


def pose_request(annotations: list[dict], names: list[str], epsilon: float, **pose) -> dict:
    checks = [
        {"instance": i, "rotation": ann["cam_R_m2c"], "translation": ann["cam_t_m2c"]}
        for i, ann in enumerate(annotations)
    ]
    return {
        "instances": [
            {"object": name, "bbox": ann["bbox"]} for ann, name in zip(annotations, names, strict=True)
        ],
        "coverage": "object",
        "epsilon": epsilon,
        "pose": {"K": annotations[0]["cam_K"], "check": checks, **pose},
    }


@pytest.fixture(scope="module")
def cases(api: InProcess, coco: dict, samples_dir: Path, manifest: dict) -> list[Case]:
    categories = {c["id"]: c["name"] for c in coco["categories"]}
    points_3d = {o["name"]: np.array(o["keypoints_3d"]) for o in manifest["objects"]}
    found = []
    for epsilon in EPSILONS:
        for image in coco["images"]:
            annotations = [a for a in coco["annotations"] if a["image_id"] == image["id"]]
            names = [categories[a["category_id"]] for a in annotations]
            body = pose_request(annotations, names, epsilon)
            result = predict_ok(api.client, (samples_dir / image["file_name"]).read_bytes(), body)
            for ann, name, answer in zip(annotations, names, result["instances"], strict=True):
                camera = np.array(ann["cam_K"])
                rotation, translation = np.array(ann["cam_R_m2c"]), np.array(ann["cam_t_m2c"])
                found.append(Case(epsilon, camera, points_3d[name], rotation, translation, answer))
    return found


def test_every_estimate_projects_inside_its_sets(cases: list[Case]) -> None:
    estimated = [c for c in cases if not c.answer["pose"]["empty"]]
    assert len(estimated) > len(cases) / 2
    for case in estimated:
        pose = case.answer["pose"]
        assert pose["method"] in {"pnp", "pnp+refined-into-set", "sampled"}
        assert in_sets(case, pose["rotation"], pose["translation"]), pose
        assert pose["largest_violation"] <= 1.0
        assert np.allclose(np.array(pose["rotation"]).T @ pose["rotation"], np.eye(3), atol=1e-9)
    for case in cases:
        pose = case.answer["pose"]
        if pose["empty"]:
            assert pose["rotation"] is None and pose["method"] == "none" and pose["inner_bound"] is None
            outer = pose["outer_bound"]
            assert outer["rotation_deg"] is None and outer["translation"] is None
            assert not outer["certified"] or "infeasible" in outer["status"]  # only emptiness is proven


def test_membership_is_what_the_sets_say(cases: list[Case]) -> None:
    """The server's check agrees with projecting the true pose into the response's sets."""
    for case in cases:
        (check,) = case.answer["pose"]["checks"]
        assert check["inside"] == in_sets(case, case.rotation, case.translation)
        assert check["inside"] == all(v is not None and v <= 1 for v in check["violations"])


@pytest.mark.parametrize("epsilon", EPSILONS)
def test_true_poses_are_in_purse_at_the_guaranteed_rate(cases: list[Case], epsilon: float) -> None:
    """Given the calibration, coverage ~ Beta(a, b) (Theorem 1); m test instances then count
    ~ BetaBinomial(m, a, b): the count must lie in its central 1 - 2 * BAND_ALPHA band."""
    chosen = [c for c in cases if c.epsilon == epsilon]
    law = chosen[0].answer["keypoints"][0]["guarantee"]
    assert law["scope"] == "object" and law["t"] > 0
    a, b = law["conditional_coverage"]["a"], law["conditional_coverage"]["b"]
    inside = sum(c.answer["pose"]["checks"][0]["inside"] for c in chosen)
    m = len(chosen)
    assert betabinom.cdf(inside, m, a, b) >= BAND_ALPHA, f"{inside}/{m} true poses in PURSE: too few"
    assert betabinom.sf(inside - 1, m, a, b) >= BAND_ALPHA, f"{inside}/{m} true poses in PURSE: too many"


def test_a_pose_far_from_the_truth_is_outside(api: InProcess, coco: dict, samples_dir: Path) -> None:
    image = coco["images"][0]
    annotations = [a for a in coco["annotations"] if a["image_id"] == image["id"]]
    names = [c["name"] for a in annotations for c in coco["categories"] if c["id"] == a["category_id"]]
    body = pose_request(annotations, names, 0.1, samples=0, outer_bound=False)
    quarter_turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    far = []
    for i, ann in enumerate(annotations):
        rotation, translation = np.array(ann["cam_R_m2c"]), np.array(ann["cam_t_m2c"])
        far.append(
            {"instance": i, "rotation": rotation.tolist(), "translation": (translation * 1.5).tolist()}
        )
        turned = (quarter_turn @ rotation).tolist()
        far.append({"instance": i, "rotation": turned, "translation": translation.tolist()})
        far.append({"instance": i, "rotation": rotation.tolist(), "translation": (-translation).tolist()})
    body["pose"]["check"] = far
    result = predict_ok(api.client, (samples_dir / image["file_name"]).read_bytes(), body)
    for instance in result["instances"]:
        checks = instance["pose"]["checks"]
        assert len(checks) == 3 and not any(c["inside"] for c in checks)
        assert all(v is None for v in checks[2]["violations"])  # behind the camera


def test_certified_outer_bounds_contain_the_true_error(cases: list[Case]) -> None:
    certified = 0
    for case in cases:
        pose = case.answer["pose"]
        outer, inner = pose["outer_bound"], pose["inner_bound"]
        if pose["empty"] or not outer["certified"]:
            continue
        certified += 1
        assert inner is not None
        assert inner["rotation_deg"] <= outer["rotation_deg"] + 1e-9
        assert inner["translation"] <= outer["translation"] * (1 + 1e-9)
        if case.answer["pose"]["checks"][0]["inside"]:
            assert geodesic_deg(pose["rotation"], case.rotation) <= outer["rotation_deg"] + 1e-9
            error = float(np.linalg.norm(np.array(pose["translation"]) - case.translation))
            assert error <= outer["translation"] * (1 + 1e-9)
    assert certified > len(cases) / 2


def test_a_pose_overlay_is_drawn(api: InProcess, coco: dict, samples_dir: Path) -> None:
    image = coco["images"][0]
    annotations = [a for a in coco["annotations"] if a["image_id"] == image["id"]]
    names = [c["name"] for a in annotations for c in coco["categories"] if c["id"] == a["category_id"]]
    body = pose_request(annotations, names, 0.1, samples=0, outer_bound=False)
    image_bytes = (samples_dir / image["file_name"]).read_bytes()
    png = {"Accept": "image/png"}
    with_pose = predict_json(api.client, image_bytes, body, headers=png)
    body.pop("pose")
    without = predict_json(api.client, image_bytes, body, headers=png)
    assert with_pose.status_code == without.status_code == 200
    assert with_pose.headers["content-type"] == "image/png"
    assert with_pose.content != without.content


def one_instance(coco: dict) -> tuple[dict, dict]:
    ann = coco["annotations"][0]
    name = next(c["name"] for c in coco["categories"] if c["id"] == ann["category_id"])
    return {"instances": [{"object": name, "bbox": ann["bbox"]}], "coverage": "object"}, ann


@pytest.mark.parametrize(
    ("K", "says"),
    [
        ([[572.0, 0.0, 320.0], [0.0, 572.0, 240.0]], "3 rows of 3"),
        ([[0.0, 0.0, 320.0], [0.0, 572.0, 240.0], [0.0, 0.0, 1.0]], "fx"),
        ([[572.0, 0.0, 320.0], [0.0, 572.0, 240.0], [0.0, 1.0, 1.0]], "last row"),
        ([[572.0, 0.0, 320.0], [0.0, 572.0, 240.0], [0.0, 0.0, math.inf]], "finite"),
        ("572", "pose.K"),
    ],
)
def test_a_malformed_camera_matrix_is_refused(
    api: InProcess, coco: dict, samples_dir: Path, K, says: str
) -> None:
    body, _ = one_instance(coco)
    image = (samples_dir / coco["images"][0]["file_name"]).read_bytes()
    # written by hand: 1e999 is a valid JSON number that parses to infinity
    raw = json.dumps({**body, "image_base64": b64(image)})[:-1] + f', "pose": {{"K": {json.dumps(K)}}}}}'
    response = api.client.post(
        "/v1/predict", content=raw.replace("Infinity", "1e999"), headers={"Content-Type": "application/json"}
    )
    assert_problem(response, 422, "pose.K", says)


def test_pose_without_object_coverage_is_refused(api: InProcess, coco: dict, samples_dir: Path) -> None:
    body, ann = one_instance(coco)
    body.update(coverage="keypoint", pose={"K": ann["cam_K"]})
    image = (samples_dir / coco["images"][0]["file_name"]).read_bytes()
    assert_problem(predict_json(api.client, image, body), 422, "pose", "coverage 'object'")


def test_bad_pose_checks_are_refused(api: InProcess, coco: dict, samples_dir: Path) -> None:
    body, ann = one_instance(coco)
    image = (samples_dir / coco["images"][0]["file_name"]).read_bytes()
    check = {"instance": 1, "rotation": ann["cam_R_m2c"], "translation": ann["cam_t_m2c"]}
    body["pose"] = {"K": ann["cam_K"], "check": [check]}
    assert_problem(predict_json(api.client, image, body), 422, "pose.check", "instance 1 does not exist")
    body["pose"]["check"] = [{**check, "instance": 0, "rotation": np.diag([1.0, 1.0, -1.0]).tolist()}]
    assert_problem(predict_json(api.client, image, body), 422, "pose.check[0].rotation", "not a rotation")


def test_an_object_without_3d_keypoints_is_refused(
    model_path: Path, coco: dict, samples_dir: Path, tmp_path: Path
) -> None:
    model = tmp_path / "model"
    model.mkdir()
    for name in ("model.onnx", "default_calibration.npz"):
        shutil.copyfile(model_path / name, model / name)
    manifest = json.loads((model_path / "manifest.json").read_text())
    body, ann = one_instance(coco)
    flat = next(o for o in manifest["objects"] if o["name"] == body["instances"][0]["object"])
    del flat["keypoints_3d"]
    (model / "manifest.json").write_text(json.dumps(manifest))
    body["pose"] = {"K": ann["cam_K"]}
    image = (samples_dir / coco["images"][0]["file_name"]).read_bytes()
    with InProcess(tmp_path / "data", admin_token=ADMIN_TOKEN, model_dir=model) as live:
        problem = assert_problem(
            predict_json(live.client, image, body), 422, "instances[0].object", "keypoints_3d"
        )
        body.pop("pose")
        assert predict_json(live.client, image, body).status_code == 200  # the same request without pose
    assert problem["status"] == 422


def test_batch_items_carry_pose_and_refuse_alone(api: InProcess, coco: dict, samples_dir: Path) -> None:
    """POST /v1/predict/batch answers pose per image; a bad pose request fails only its own item."""
    body, ann = one_instance(coco)
    image = (samples_dir / coco["images"][0]["file_name"]).read_bytes()
    good = {**body, "pose": {"K": ann["cam_K"], "samples": 10}}
    bad = {**body, "coverage": "keypoint", "pose": {"K": ann["cam_K"]}}
    parts = []
    for index, request in enumerate([good, bad]):
        parts.append((f"image_{index}", ("image.jpg", image, "image/jpeg")))
        parts.append((f"request_{index}", (None, json.dumps(request).encode(), "application/json")))
    response = api.client.post("/v1/predict/batch", files=parts)
    assert response.status_code == 200, response.text
    first, second = response.json()["items"]
    assert first["status"] == 200 and first["result"]["instances"][0]["pose"]["method"] != "none"
    assert second["status"] == 422 and "coverage 'object'" in second["problem"]["detail"]


def test_the_rotation_search_tightens_a_certified_bound(
    api: InProcess, coco: dict, samples_dir: Path
) -> None:
    body, ann = one_instance(coco)
    image = (samples_dir / coco["images"][0]["file_name"]).read_bytes()
    check = [{"instance": 0, "rotation": ann["cam_R_m2c"], "translation": ann["cam_t_m2c"]}]
    bounds = []
    for options in ({"outer_programs": 0}, {}):  # the whole space, the search
        body["pose"] = {"K": ann["cam_K"], "samples": 30, "check": check, **options}
        pose = predict_ok(api.client, image, body)["instances"][0]["pose"]
        outer = pose["outer_bound"]
        assert outer["certified"], outer
        assert outer["rotation_over_inner"] >= 1 and outer["translation_over_inner"] >= 1, outer
        bounds.append(outer)
        if pose["checks"][0]["inside"]:
            assert geodesic_deg(pose["rotation"], ann["cam_R_m2c"]) <= outer["rotation_deg"]
    whole, searched = bounds
    assert searched["rotation_deg"] < whole["rotation_deg"]
    assert searched["translation"] <= whole["translation"] * (1 + 1e-9)
    body["pose"]["outer_splits"] = 3  # the older branch-and-bound, removed: an unknown field
    assert_problem(predict_json(api.client, image, body), 422, "pose.outer_splits")
    body["pose"] = {"K": ann["cam_K"], "outer_programs": 2001}
    assert_problem(predict_json(api.client, image, body), 422, "pose.outer_programs")
