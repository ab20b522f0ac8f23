"""Calibration administration end to end: upload, job, activate, predict, roll back, append, auth."""

from __future__ import annotations

import hashlib
import math
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.api.in_process import InProcess
from tests.predict_client import instances_of, predict_ok
from tests.samples import Sample, batch_zip, count_instances, samples_by_image
from tests.service_calls import ADMIN_TOKEN, assert_problem

FUNCTIONS = ("peak", "var", "cov")
REPORTED_EPSILONS = (0.05, 0.1, 0.2)


@pytest.fixture(scope="module")
def first_image(samples: list[Sample]) -> tuple[bytes, list[Sample]]:
    path, group = next(iter(samples_by_image(samples).items()))
    return path.read_bytes(), group


def active(api: InProcess) -> int:
    response = api.client.get("/readyz")
    assert response.status_code == 200, response.text
    return response.json()["active_calibration"]


def detail(api: InProcess, version: int) -> dict:
    response = api.client.get(f"/v1/admin/calibrations/{version}", headers=api.admin)
    assert response.status_code == 200, response.text
    return response.json()


def activate(api: InProcess, version: int, reason: str, force: bool = False) -> dict:
    response = api.client.post(
        f"/v1/admin/calibrations/{version}/activate",
        json={"reason": reason, "force": force},
        headers=api.admin,
    )
    assert response.status_code == 200, response.text
    return response.json()


def result(version: int, instances: int, activated: bool, added: int) -> dict:
    """A calibration job's result when nothing was dropped or rejected."""
    return {
        "version": version,
        "instances": instances,
        "activated": activated,
        "added": added,
        "duplicates_dropped": 0,
        "rejected": 0,
        "rejections": [],
    }


def used_version(api: InProcess, image: tuple[bytes, list[Sample]], version: int | None = None) -> dict:
    parameters: dict = {"instances": instances_of(image[1])}
    if version is not None:
        parameters["calibration_version"] = version
    return predict_ok(api.client, image[0], parameters)


def test_upload_job_activate_predict_and_roll_back(
    api: InProcess, samples_dir: Path, coco: dict, samples: list[Sample], first_image
) -> None:
    before = api.versions()
    previous = active(api)
    log_before = api.client.get("/v1/admin/activations", headers=api.admin).json()["activations"]
    body = batch_zip(samples_dir, coco)
    total = count_instances(coco)

    response = api.upload(body, name="samples-batch", note="end-to-end test")
    assert response.status_code == 202, response.text
    job = response.json()
    assert job["kind"] == "calibration" and job["state"] in ("queued", "running", "succeeded")
    assert job["total"] == total and job["errors"] == []
    assert response.headers["location"] == f"/v1/admin/jobs/{job['id']}"

    job = api.wait_job(job["id"])
    assert job["state"] == "succeeded", job
    assert job["done"] == job["total"] == total
    assert job["errors"] == [] and job["finished_at"] is not None
    version = job["result"]["version"]
    assert job["result"] == result(version, total, False, total)
    assert job["version"] == version
    assert api.versions() == [*before, version]
    assert active(api) == previous  # not activated without activate=true
    assert api.upload_workspaces() == [], "the upload workspace was not removed"

    summary = detail(api, version)
    assert summary["note"] == "end-to-end test" and summary["author"] == "admin"
    assert summary["instances"] == total and summary["parent_version"] is None and not summary["active"]
    assert summary["source_batches"] == [
        {"name": "samples-batch", "sha256": hashlib.sha256(body).hexdigest(), "instances": total}
    ]
    assert sum(summary["objects"].values()) == total

    # predict with the new version before activating it; n is the version's labeled count
    pinned = used_version(api, first_image, version)
    assert pinned["calibration"]["version"] == version
    for instance in pinned["instances"]:
        for keypoint in instance["keypoints"]:
            assert keypoint["guarantee"]["n"] == summary["labeled_per_keypoint"][keypoint["name"]]
    assert used_version(api, first_image)["calibration"]["version"] == previous

    refused = api.client.post(
        f"/v1/admin/calibrations/{version}/activate", json={"reason": "new batch"}, headers=api.admin
    )
    problem = assert_problem(refused, 409, "activation refused", "force")
    assert problem["comparison"]["against"] == previous and not problem["comparison"]["allowed"]
    assert active(api) == previous
    entry = activate(api, version, "new batch", force=True)
    assert (entry["version"], entry["who"], entry["reason"]) == (version, "admin", "new batch")
    assert active(api) == version
    assert used_version(api, first_image)["calibration"]["version"] == version
    assert used_version(api, first_image) == pinned

    listed = api.client.get("/v1/admin/calibrations", headers=api.admin).json()
    assert listed["active_version"] == version
    assert [v["version"] for v in listed["versions"] if v["active"]] == [version]

    rollback = activate(api, previous, "roll back")
    assert rollback["version"] == previous and rollback["seq"] > entry["seq"]
    assert active(api) == previous
    assert used_version(api, first_image)["calibration"]["version"] == previous
    assert api.versions() == [*before, version]  # rollback loses nothing

    log = api.client.get("/v1/admin/activations", headers=api.admin).json()
    assert log["active_version"] == previous
    entries = log["activations"]
    assert entries[: len(log_before)] == log_before  # append-only
    new = entries[len(log_before) :]
    assert [(e["version"], e["reason"], e["who"]) for e in new] == [
        (version, "new batch", "admin"),
        (previous, "roll back", "admin"),
    ]
    seqs = [e["seq"] for e in entries]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    times = [e["activated_at"] for e in entries]
    assert times == sorted(times)


def test_append_to_a_version_and_activate_on_success(
    api: InProcess, samples_dir: Path, coco: dict, first_image
) -> None:
    parent = active(api)
    parent_detail = detail(api, parent)
    body = batch_zip(samples_dir, coco, images=3)
    batch_count = count_instances(coco, images=3)

    job = api.calibrate(body, append_to=parent, activate=True, note="appended")
    version = job["result"]["version"]
    assert job["result"] == result(version, parent_detail["instances"] + batch_count, True, batch_count)
    assert job["total"] == job["done"] == batch_count  # only the batch is scored
    assert active(api) == version
    assert used_version(api, first_image)["calibration"]["version"] == version

    child = detail(api, version)
    assert child["parent_version"] == parent and child["active"]
    assert child["instances"] == parent_detail["instances"] + batch_count
    assert child["source_batches"][:-1] == parent_detail["source_batches"]
    assert child["source_batches"][-1]["instances"] == batch_count
    assert child["source_batches"][-1]["sha256"] == hashlib.sha256(body).hexdigest()
    objects = dict(parent_detail["objects"])
    categories = {c["id"]: c["name"] for c in coco["categories"]}
    kept = {image["id"] for image in coco["images"][:3]}
    for ann in coco["annotations"]:
        if ann["image_id"] in kept:
            name = categories[ann["category_id"]]
            objects[name] = objects.get(name, 0) + 1
    assert child["objects"] == objects
    for name, n in parent_detail["labeled_per_keypoint"].items():
        assert child["labeled_per_keypoint"][name] >= n
    assert sum(child["labeled_per_keypoint"].values()) > sum(parent_detail["labeled_per_keypoint"].values())

    log = api.client.get("/v1/admin/activations", headers=api.admin).json()["activations"]
    assert log[-1]["version"] == version and log[-1]["reason"] == "activated on creation"
    activate(api, parent, "restore")  # leave the active version as found


def test_version_detail_reports_thresholds(api: InProcess, manifest: dict) -> None:
    version = active(api)
    body = detail(api, version)
    keypoints = [k["name"] for k in manifest["keypoints"]]
    objects = [o["name"] for o in manifest["objects"]]
    assert body["version"] == version and body["active"]
    assert set(body["labeled_per_keypoint"]) == set(keypoints)
    assert set(body["complete_per_object"]) == set(objects)
    assert body["normalization"]["mode"] == manifest["heatmap"]["normalization"]
    rows = {(r["nonconformity"], r["epsilon"]): r for r in body["thresholds"]}
    assert set(rows) == {(f, e) for f in FUNCTIONS for e in REPORTED_EPSILONS}
    for function in FUNCTIONS:
        for scope, names in (("keypoint", keypoints), ("object", objects)):
            previous = {name: math.inf for name in names}
            for epsilon in REPORTED_EPSILONS:  # larger epsilon, smaller (or equal) threshold
                values = rows[(function, epsilon)][scope]
                assert set(values) == set(names)
                for name, value in values.items():
                    current = math.inf if value is None else value
                    assert value is None or (math.isfinite(value) and value >= 0)
                    assert current <= previous[name], (function, scope, name, epsilon)
                    previous[name] = current
    for name, n in body["labeled_per_keypoint"].items():  # null exactly when t = floor((n+1) eps) = 0
        assert (rows[("peak", 0.05)]["keypoint"][name] is None) == (math.floor((n + 1) * 0.05) == 0)


def test_missing_version_and_job_are_404(api: InProcess) -> None:
    missing = max(api.versions()) + 100
    assert_problem(api.client.get(f"/v1/admin/calibrations/{missing}", headers=api.admin), 404)
    response = api.client.post(
        f"/v1/admin/calibrations/{missing}/activate", json={"reason": "x"}, headers=api.admin
    )
    assert_problem(response, 404, str(missing))
    assert_problem(api.client.get("/v1/admin/jobs/nope", headers=api.admin), 404)


@pytest.mark.parametrize("version", ["0", "-1", str(2**31), str(2**70), "one"])
def test_out_of_range_version_numbers_are_422(api: InProcess, version: str) -> None:
    """Not 500: the store keeps version numbers as 32-bit integers >= 1."""
    versions = api.versions()
    assert_problem(api.client.get(f"/v1/admin/calibrations/{version}", headers=api.admin), 422, "version")
    response = api.client.post(
        f"/v1/admin/calibrations/{version}/activate", json={"reason": "x"}, headers=api.admin
    )
    assert_problem(response, 422, "version")
    assert api.versions() == versions


ADMIN_ROUTES = [
    ("GET", "/v1/admin/calibrations"),
    ("GET", "/v1/admin/calibrations/1"),
    ("GET", "/v1/admin/calibrations/1/compare"),
    ("POST", "/v1/admin/calibrations/1/activate"),
    ("GET", "/v1/admin/activations"),
    ("GET", "/v1/admin/jobs/abc"),
    ("POST", "/v1/admin/jobs/abc/retry"),
    ("POST", "/v1/admin/calibrations"),
    ("GET", "/v1/admin/audit"),
    ("GET", "/v1/admin/store"),
]


@pytest.mark.parametrize(("method", "path"), ADMIN_ROUTES)
@pytest.mark.parametrize("authorization", [None, "Bearer wrong-token", f"Basic {ADMIN_TOKEN}", "Bearer"])
def test_admin_needs_the_bearer_token(api: InProcess, method: str, path: str, authorization) -> None:
    headers = {"Content-Type": "application/zip"}
    if authorization is not None:
        headers["Authorization"] = authorization
    versions = api.versions()
    response = api.client.request(method, path, headers=headers, content=b"PK")
    assert_problem(response, 401, "Bearer")
    assert response.headers["www-authenticate"] == "Bearer"
    assert api.versions() == versions


def test_each_authorization_mistake_gets_its_own_401(api: InProcess) -> None:
    """No header, a token without 'Bearer ', a wrong token: three texts, each naming the fix."""
    said = {}
    for mistake, headers in {
        "none": {},
        "no bearer": {"Authorization": ADMIN_TOKEN},
        "wrong": {"Authorization": "Bearer wrong-token-0123456789"},
    }.items():
        response = api.client.get("/v1/admin/activations", headers=headers)
        said[mistake] = assert_problem(response, 401)["detail"]
    assert said["none"].startswith("No Authorization header"), said
    assert "does not start with 'Bearer '" in said["no bearer"], said
    assert said["wrong"].startswith("The bearer token is not an admin token"), said
    assert "CKS_ADMIN_TOKEN" in said["wrong"] and "wrong-token" not in said["wrong"], said
    assert ADMIN_TOKEN not in said["no bearer"], said  # a token is never echoed
    assert len(set(said.values())) == 3, said
    assert all("'Authorization: Bearer <admin token>'" in text for text in said.values()), said


@pytest.mark.parametrize("content_type", [None, "application/x-www-form-urlencoded"])
def test_a_json_body_without_its_content_type_is_told_to_send_it(api: InProcess, content_type) -> None:
    """curl -d alone sends application/x-www-form-urlencoded: the 422 says which header to add."""
    headers = {**api.admin, **({"Content-Type": content_type} if content_type else {})}
    body = b'{"force": true, "reason": "trying"}'
    response = api.client.post("/v1/admin/calibrations/1/activate", content=body, headers=headers)
    problem = assert_problem(response, 422, "must be JSON sent with 'Content-Type: application/json'")
    sent = f"Content-Type: {content_type}" if content_type else "no Content-Type"
    assert f"this request had {sent}" in problem["detail"], problem
    assert "valid dictionary" not in problem["detail"], problem


@pytest.fixture(scope="module")
def no_admin_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[InProcess]:
    with InProcess(tmp_path_factory.mktemp("no-admin") / "data") as live:
        yield live


@pytest.mark.parametrize(("method", "path"), ADMIN_ROUTES)
def test_admin_is_disabled_without_a_configured_token(
    no_admin_server: InProcess, method: str, path: str, first_image
) -> None:
    for headers in ({}, {"Authorization": f"Bearer {ADMIN_TOKEN}"}):
        response = no_admin_server.client.request(method, path, headers=headers, content=b"PK")
        assert_problem(response, 403, "CKS_ADMIN_TOKEN", "CKS_ADMIN_TOKENS_FILE")
    assert used_version(no_admin_server, first_image)["calibration"]["version"] == 1  # predict still works
