"""POST /v1/predict end to end on the bundled sample images, in process through the ASGI app.

Everything here holds for any model (structure, consistency, monotonicity) except
``test_sets_cover_labeled_keypoints_at_the_expected_rate``, which measures the model's
calibrated coverage on the labeled samples and needs the real bundled detector.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from tests.api.in_process import InProcess
from tests.predict_client import (
    contains,
    extent,
    instances_of,
    predict_json,
    predict_multipart,
    predict_ok,
)
from tests.samples import Sample, samples_by_image

FUNCTIONS = ("peak", "var", "cov")
SET_TYPES = {"peak": {"ball"}, "var": {"ball"}, "cov": {"ellipse"}}


@pytest.fixture(scope="module")
def images(samples: list[Sample]) -> list[tuple[bytes, list[Sample]]]:
    """Every sample image's bytes with its labeled instances."""
    return [(path.read_bytes(), group) for path, group in samples_by_image(samples).items()]


@pytest.fixture(scope="module")
def model_info(api: InProcess) -> dict:
    response = api.client.get("/v1/model")
    assert response.status_code == 200, response.text
    return response.json()


def check_guarantee(guarantee: dict, epsilon: float, scope: str) -> None:
    n, t = guarantee["n"], guarantee["t"]
    assert guarantee["scope"] == scope
    assert guarantee["epsilon"] == pytest.approx(epsilon)
    assert 0 <= t <= n
    assert t == math.floor((n + 1) * epsilon) or guarantee["delta"] is not None
    assert guarantee["coverage_lower_bound"] == pytest.approx(1 - epsilon)
    if n > 0:
        assert guarantee["coverage_upper_bound"] == pytest.approx(min(1.0, 1 - epsilon + 1 / (n + 1)))
    assert guarantee["conditional_coverage"] == {"a": n + 1 - t, "b": t}


def test_multipart_and_base64_json_give_the_same_answer(api: InProcess, images) -> None:
    for image, group in images:
        parameters = {"instances": instances_of(group)}
        by_form = predict_multipart(api.client, image, parameters)
        by_json = predict_json(api.client, image, parameters)
        assert by_form.status_code == by_json.status_code == 200, (by_form.text, by_json.text)
        assert by_form.json() == by_json.json()


@pytest.mark.parametrize("function", FUNCTIONS)
def test_response_structure(api: InProcess, images, model_info: dict, function: str) -> None:
    manifest = model_info["manifest"]
    names = [k["name"] for k in manifest["keypoints"]]
    objects = {o["name"]: o["keypoints"] for o in manifest["objects"]}
    active = api.client.get("/readyz").json()["active_calibration"]
    for image, group in images:
        parameters = {"instances": instances_of(group), "nonconformity": function, "epsilon": 0.1}
        body = predict_ok(api.client, image, parameters)
        height, width = cv2.imdecode(np.frombuffer(image, np.uint8), cv2.IMREAD_UNCHANGED).shape[:2]
        assert body["image"] == {"width": width, "height": height}
        assert body["model"] == {key: model_info[key] for key in ("name", "hash", "variant")}
        assert body["calibration"] == {
            "version": active,
            "nonconformity": function,
            "coverage": "keypoint",
            "epsilon": 0.1,
            "delta": None,
        }
        assert len(body["instances"]) == len(group)
        for sample, instance in zip(group, body["instances"], strict=True):
            assert instance["object"] == sample.object
            assert instance["bbox"] == pytest.approx(sample.bbox)
            assert [k["index"] for k in instance["keypoints"]] == objects[sample.object]
            for keypoint in instance["keypoints"]:
                assert keypoint["name"] == names[keypoint["index"]]
                assert keypoint["statistics"] is None
                region = keypoint["set"]
                assert region["type"] in SET_TYPES[function] | {"unbounded"}, region
                check_guarantee(keypoint["guarantee"], 0.1, "keypoint")
                if region["type"] == "unbounded":
                    assert keypoint["guarantee"]["t"] == 0
                    continue
                assert keypoint["guarantee"]["t"] >= 1
                assert all(math.isfinite(v) for v in keypoint["point"])
                assert region["center"] == pytest.approx(keypoint["point"])
                assert contains(region, tuple(keypoint["point"]))
                if region["type"] == "ball":
                    assert region["radius"] >= 0
                else:
                    (a, b), (c, d) = region["shape_matrix"]
                    assert b == pytest.approx(c)
                    assert a > 0 and d > 0 and a * d - b * c > 0  # positive definite
                    minor, major = region["semi_axes"]
                    assert 0 < minor <= major
                    assert math.isfinite(region["angle_deg"])


def test_include_statistics(api: InProcess, images, manifest: dict) -> None:
    image, group = images[0]
    body = predict_ok(api.client, image, {"instances": instances_of(group), "include_statistics": True})
    height, width = manifest["output"]["height"], manifest["output"]["width"]
    for instance in body["instances"]:
        for keypoint in instance["keypoints"]:
            stats = keypoint["statistics"]
            assert 0 < stats["peak_probability"] <= 1
            for x, y in (stats["peak"], stats["mean"]):
                assert 0 <= x <= width and 0 <= y <= height  # heatmap pixels
            assert stats["gamma"] >= 0
            (a, b), (c, d) = stats["covariance"]
            assert b == pytest.approx(c) and a >= 0 and d >= 0
    plain = predict_ok(api.client, image, {"instances": instances_of(group)})
    for with_stats, without in zip(body["instances"], plain["instances"], strict=True):
        for k1, k2 in zip(with_stats["keypoints"], without["keypoints"], strict=True):
            assert k1["set"] == k2["set"]


@pytest.mark.parametrize("function", FUNCTIONS)
def test_pac_sets_are_at_least_as_large(api: InProcess, images, function: str) -> None:
    for image, group in images[:6]:
        base = {"instances": instances_of(group), "nonconformity": function, "epsilon": 0.2}
        marginal = predict_ok(api.client, image, base)
        pac = predict_ok(api.client, image, {**base, "delta": 0.1})
        assert pac["calibration"]["delta"] == 0.1
        for inst, inst_pac in zip(marginal["instances"], pac["instances"], strict=True):
            for kp, kp_pac in zip(inst["keypoints"], inst_pac["keypoints"], strict=True):
                g, g_pac = kp["guarantee"], kp_pac["guarantee"]
                assert g_pac["delta"] == 0.1 and g_pac["n"] == g["n"]
                assert g_pac["t"] <= g["t"]
                if g_pac["t"] > 0:
                    assert g_pac["pac_failure_probability"] <= 0.1 + 1e-12
                assert kp_pac["point"] == pytest.approx(kp["point"])
                small, large = extent(kp["set"]), extent(kp_pac["set"])
                assert large[0] >= small[0] * (1 - 1e-9) and large[1] >= small[1] * (1 - 1e-9), (
                    kp["set"],
                    kp_pac["set"],
                )


@pytest.mark.parametrize("function", FUNCTIONS)
def test_object_coverage_shares_one_guarantee_per_instance(api: InProcess, images, function: str) -> None:
    for image, group in images[:6]:
        parameters = {"instances": instances_of(group), "nonconformity": function, "coverage": "object"}
        body = predict_ok(api.client, image, parameters)
        assert body["calibration"]["coverage"] == "object"
        for instance in body["instances"]:
            guarantees = [kp["guarantee"] for kp in instance["keypoints"]]
            assert all(g == guarantees[0] for g in guarantees), guarantees
            check_guarantee(guarantees[0], 0.1, "object")
            for keypoint in instance["keypoints"]:
                assert contains(keypoint["set"], tuple(keypoint["point"]))


def test_tiny_epsilon_gives_unbounded_sets(api: InProcess, images) -> None:
    image, group = images[0]
    probe = predict_ok(api.client, image, {"instances": instances_of(group)})
    largest_n = max(kp["guarantee"]["n"] for inst in probe["instances"] for kp in inst["keypoints"])
    epsilon = min(0.0005, 0.5 / (largest_n + 1))  # (n + 1) * epsilon < 1: t = 0 for every keypoint
    for function in FUNCTIONS:
        parameters = {"instances": instances_of(group), "nonconformity": function, "epsilon": epsilon}
        body = predict_ok(api.client, image, parameters)
        for instance in body["instances"]:
            for keypoint in instance["keypoints"]:
                assert keypoint["set"]["type"] == "unbounded", keypoint
                assert keypoint["set"]["reason"]
                assert keypoint["guarantee"]["t"] == 0
                assert all(math.isfinite(v) for v in keypoint["point"])


@pytest.mark.parametrize("form", ["json", "multipart"])
def test_the_png_operation_returns_the_image_with_sets_drawn(api: InProcess, images, form: str) -> None:
    image, group = images[0]
    send = predict_json if form == "json" else predict_multipart
    response = send(api.client, image, {"instances": instances_of(group)}, path="/v1/predict/png")
    older = send(api.client, image, {"instances": instances_of(group)}, headers={"Accept": "image/png"})
    assert response.status_code == 200, response.text
    assert older.content == response.content  # Accept: image/png on /v1/predict, as before
    assert response.headers["content-type"] == "image/png"
    assert response.content.startswith(b"\x89PNG\r\n\x1a\n")
    drawn = cv2.imdecode(np.frombuffer(response.content, np.uint8), cv2.IMREAD_COLOR)
    original = cv2.imdecode(np.frombuffer(image, np.uint8), cv2.IMREAD_COLOR)
    assert drawn is not None and drawn.shape == original.shape
    assert np.abs(drawn.astype(int) - original.astype(int)).sum() > 0  # something was drawn


def test_explicit_calibration_version(api: InProcess, images) -> None:
    image, group = images[0]
    active = api.client.get("/readyz").json()["active_calibration"]
    implicit = predict_ok(api.client, image, {"instances": instances_of(group)})
    explicit = predict_ok(
        api.client, image, {"instances": instances_of(group), "calibration_version": active}
    )
    assert explicit == implicit


@pytest.mark.parametrize("function", FUNCTIONS)
def test_sets_cover_labeled_keypoints_at_the_expected_rate(api: InProcess, images, function: str) -> None:
    """Model quality: at epsilon 0.1 the sets hold >= 75% of the labeled sample keypoints.

    Passes only with the real bundled detector (a stand-in with random weights is not expected to).
    """
    inside = total = 0
    for image, group in images:
        parameters = {"instances": instances_of(group), "nonconformity": function, "epsilon": 0.1}
        body = predict_ok(api.client, image, parameters)
        for sample, instance in zip(group, body["instances"], strict=True):
            for (x, y, v), keypoint in zip(sample.keypoints, instance["keypoints"], strict=True):
                if v > 0:
                    total += 1
                    inside += contains(keypoint["set"], (x, y))
    assert total > 0
    rate = inside / total
    assert rate >= 0.75, (
        f"{function}: {inside}/{total} = {rate:.3f} labeled keypoints inside the eps=0.1 sets"
    )
