"""Mondrian strata end to end in process (the ASGI app): the bundled version's difficulty bins, predictions
answered by a difficulty bin or a caller group, a group-stratified upload, and the refusals."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.api.in_process import InProcess
from tests.predict_client import instances_of, predict_json, predict_ok
from tests.samples import Sample, batch_zip, samples_by_image
from tests.service_calls import assert_problem

GROUPS = ("cam-a", "cam-b")


def _group_of(image_id: int) -> str:
    return GROUPS[image_id % 2]


def _with_groups(doc: dict, files: dict[str, bytes]) -> None:
    for annotation in doc["annotations"]:
        annotation["group"] = _group_of(annotation["image_id"])


@pytest.fixture(scope="module")
def first_image(samples: list[Sample]) -> tuple[bytes, list[Sample]]:
    path, group = next(iter(samples_by_image(samples).items()))
    return path.read_bytes(), group


@pytest.fixture(scope="module")
def grouped_version(api: InProcess, samples_dir: Path, coco: dict) -> int:
    body = batch_zip(samples_dir, coco, mutate=_with_groups)
    return api.calibrate(body, stratify="group", name="grouped")["version"]


def _detail(api: InProcess, version: int) -> dict:
    response = api.client.get(f"/v1/admin/calibrations/{version}", headers=api.admin)
    assert response.status_code == 200, response.text
    return response.json()


def _keypoints(body: dict) -> list[dict]:
    return [kp for instance in body["instances"] for kp in instance["keypoints"]]


def test_the_bundled_version_ships_with_difficulty_strata(api: InProcess, manifest: dict) -> None:
    detail = _detail(api, 1)
    strata = detail["strata"]
    assert strata["spec"] == {
        "difficulty": {"signals": ["gamma", "peak_probability"], "bins": 3, "min_instances": 30},
        "group": False,
    }
    names = {k["index"]: k["name"] for k in manifest["keypoints"]}
    for channel, keyed in strata["bins"].items():
        bins = keyed["*"]
        assert min(bins["counts"]) >= 30
        assert sum(bins["counts"]) == detail["labeled_per_keypoint"][names[int(channel)]]
        assert len(bins["counts"]) == sum(len(inner) + 1 for inner in bins["inner_edges"])


def test_difficulty_strata_answer_each_keypoint_from_its_bin(api: InProcess, first_image) -> None:
    image, group = first_image
    parameters = {"instances": instances_of(group), "include_statistics": True}
    pooled = predict_ok(api.client, image, parameters)
    stratified = predict_ok(api.client, image, {**parameters, "stratify": "difficulty"})
    strata = _detail(api, 1)["strata"]["bins"]
    differ = 0
    for before, after in zip(_keypoints(pooled), _keypoints(stratified), strict=True):
        stratum = after["guarantee"]["stratum"]
        assert "stratum" not in before["guarantee"]  # a response without stratify keeps its shape
        assert stratum["kind"] == "difficulty" and stratum["conditional"] and stratum["fallback"] is None
        bins = strata[str(after["index"])]["*"]
        assert after["guarantee"]["n"] == bins["counts"][stratum["bin"]] < before["guarantee"]["n"]
        for edge in stratum["edges"]:  # the keypoint's own signal lies in its bin
            value = after["statistics"][edge["signal"]]
            assert edge["low"] is None or value >= edge["low"]
            assert edge["high"] is None or value < edge["high"]
        differ += after["set"] != before["set"]
    assert differ > 0


def test_difficulty_bins_too_small_for_epsilon_are_refused_or_fall_back(api: InProcess, first_image) -> None:
    image, group = first_image
    parameters = {"instances": instances_of(group), "stratify": "difficulty", "epsilon": 0.003}
    assert_problem(
        predict_json(api.client, image, parameters),
        422,
        "too few",
        "epsilon 0.003",
        "needs n >= 333",
        "group_fallback",
    )
    body = predict_ok(api.client, image, {**parameters, "group_fallback": "pooled"})
    for keypoint in _keypoints(body):
        stratum = keypoint["guarantee"]["stratum"]
        assert stratum["kind"] == "pooled" and not stratum["conditional"] and "too few" in stratum["fallback"]
        assert keypoint["set"]["type"] != "unbounded"


def test_a_group_stratified_upload_knows_its_groups(api: InProcess, grouped_version: int) -> None:
    strata = _detail(api, grouped_version)["strata"]
    assert strata["spec"] == {"difficulty": None, "group": True}
    assert strata["groups"] == list(GROUPS)


def test_prediction_with_a_group_uses_that_groups_calibration(
    api: InProcess, grouped_version: int, first_image, coco: dict, manifest: dict
) -> None:
    image, group = first_image
    instances = [{**instance, "group": "cam-a"} for instance in instances_of(group)]
    parameters = {
        "instances": instances,
        "stratify": "group",
        "epsilon": 0.5,
        "calibration_version": grouped_version,
        "group_fallback": "pooled",
    }
    body = predict_ok(api.client, image, parameters)
    categories = {c["id"]: c["name"] for c in coco["categories"]}
    objects = {o["name"]: o["keypoints"] for o in manifest["objects"]}
    labeled: dict[int, int] = {}  # keypoint channel -> labeled instances of group cam-a
    for annotation in coco["annotations"]:
        if _group_of(annotation["image_id"]) == "cam-a":
            channels = objects[categories[annotation["category_id"]]]
            for channel, v in zip(channels, annotation["keypoints"][2::3], strict=True):
                labeled[channel] = labeled.get(channel, 0) + (v > 0)
    answered = 0
    for keypoint in _keypoints(body):
        stratum, n = keypoint["guarantee"]["stratum"], labeled.get(keypoint["index"], 0)
        if n >= 1:  # t = floor((n + 1) / 2) >= 1
            assert stratum == {
                "kind": "group",
                "group": "cam-a",
                "bin": None,
                "edges": None,
                "conditional": True,
                "fallback": None,
            }
            assert keypoint["guarantee"]["n"] == n
            answered += 1
        else:
            assert stratum["kind"] == "pooled" and "n = 0" in stratum["fallback"]
    assert answered > 0


def test_unknown_or_missing_groups_are_refused_naming_the_known_ones(
    api: InProcess, grouped_version: int, first_image
) -> None:
    image, group = first_image
    base = {"stratify": "group", "epsilon": 0.5, "calibration_version": grouped_version}
    unknown = [{**instance, "group": "cam-z"} for instance in instances_of(group)]
    assert_problem(
        predict_json(api.client, image, {**base, "instances": unknown}),
        422,
        "instances[0]",
        "'cam-z' is unknown",
        "'cam-a', 'cam-b'",
    )
    assert_problem(
        predict_json(api.client, image, {**base, "instances": instances_of(group)}),
        422,
        "names no group",
        "'cam-a', 'cam-b'",
    )
    body = predict_ok(api.client, image, {**base, "instances": unknown, "group_fallback": "pooled"})
    for keypoint in _keypoints(body):
        assert keypoint["guarantee"]["stratum"]["kind"] == "pooled"
        assert "'cam-z' is unknown" in keypoint["guarantee"]["stratum"]["fallback"]


def test_strata_a_version_lacks_are_refused(api: InProcess, grouped_version: int, first_image) -> None:
    image, group = first_image
    instances = [{**instance, "group": "cam-a"} for instance in instances_of(group)]
    assert_problem(
        predict_json(api.client, image, {"instances": instances, "stratify": "group"}),
        422,
        "version 1 has no group strata",
        "stratify=group",
    )
    grouped = {"instances": instances, "stratify": "difficulty", "calibration_version": grouped_version}
    assert_problem(predict_json(api.client, image, grouped), 422, "no difficulty strata")
    by_object = {"instances": instances, "stratify": "difficulty", "coverage": "object"}
    assert_problem(predict_json(api.client, image, by_object), 422, "coverage=keypoint")
    assert_problem(
        predict_json(api.client, image, {"instances": instances, "stratify": "bogus"}), 422, "stratify"
    )


def test_uploads_asking_for_groups_without_labels_or_unknown_strata_are_refused(
    api: InProcess, samples_dir: Path, coco: dict
) -> None:
    body = batch_zip(samples_dir, coco, images=2)
    assert_problem(api.upload(body, stratify="group"), 422, "group labels", '"group"')
    assert_problem(api.upload(body, stratify="bogus"), 422, "stratify", "difficulty+group")
