"""Calibration administration end to end: upload, job, activate, predict, roll back, append, auth."""

from __future__ import annotations

import hashlib
import math
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.live.server import LiveServer
from tests.predict_client import instances_of, predict_ok
from tests.samples import Sample, batch_zip, count_instances, samples_by_image
from tests.service_calls import ADMIN_TOKEN, assert_problem

FUNCTIONS = ("peak", "var", "cov")
REPORTED_EPSILONS = (0.05, 0.1, 0.2)


@pytest.fixture(scope="module")
def first_image(samples: list[Sample]) -> tuple[bytes, list[Sample]]:
    path, group = next(iter(samples_by_image(samples).items()))
    return path.read_bytes(), group


def active(server: LiveServer) -> int:
    response = server.client.get("/readyz")
    assert response.status_code == 200, response.text
    return response.json()["active_calibration"]


def detail(server: LiveServer, version: int) -> dict:
    response = server.client.get(f"/v1/admin/calibrations/{version}", headers=server.admin)
    assert response.status_code == 200, response.text
    return response.json()


def activate(server: LiveServer, version: int, reason: str, force: bool = False) -> dict:
    response = server.client.post(
        f"/v1/admin/calibrations/{version}/activate",
        json={"reason": reason, "force": force},
        headers=server.admin,
    )
    assert response.status_code == 200, response.text
    return response.json()


def result(version: int, instances: int, activated: bool, added: int) -> dict:
    """A calibration job's result when nothing was dropped or rejected."""
    return {"version": version, "instances": instances, "activated": activated, "added": added,
            "duplicates_dropped": 0, "rejected": 0, "rejections": []}  # fmt: skip


def used_version(server: LiveServer, image: tuple[bytes, list[Sample]], version: int | None = None) -> dict:
    parameters: dict = {"instances": instances_of(image[1])}
    if version is not None:
        parameters["calibration_version"] = version
    return predict_ok(server.client, image[0], parameters)


def test_upload_job_activate_predict_and_roll_back(
    server: LiveServer, samples_dir: Path, coco: dict, samples: list[Sample], first_image
) -> None:
    before = server.versions()
    previous = active(server)
    log_before = server.client.get("/v1/admin/activations", headers=server.admin).json()["activations"]
    body = batch_zip(samples_dir, coco)
    total = count_instances(coco)

    response = server.upload(body, name="samples-batch", note="end-to-end test")
    assert response.status_code == 202, response.text
    job = response.json()
    assert job["kind"] == "calibration" and job["state"] in ("queued", "running", "succeeded")
    assert job["total"] == total and job["errors"] == []
    assert response.headers["location"] == f"/v1/admin/jobs/{job['id']}"

    job = server.wait_job(job["id"])
    assert job["state"] == "succeeded", job
    assert job["done"] == job["total"] == total
    assert job["errors"] == [] and job["finished_at"] is not None
    version = job["result"]["version"]
    assert job["result"] == result(version, total, False, total)
    assert job["version"] == version
    assert server.versions() == [*before, version]
    assert active(server) == previous  # not activated without activate=true
    assert server.upload_workspaces() == [], "the upload workspace was not removed"

    summary = detail(server, version)
    assert summary["note"] == "end-to-end test" and summary["author"] == "admin"
    assert summary["instances"] == total and summary["parent_version"] is None and not summary["active"]
    assert summary["source_batches"] == [
        {"name": "samples-batch", "sha256": hashlib.sha256(body).hexdigest(), "instances": total}
    ]
    assert sum(summary["objects"].values()) == total

    # predict with the new version before activating it; n is the version's labeled count
    pinned = used_version(server, first_image, version)
    assert pinned["calibration"]["version"] == version
    for instance in pinned["instances"]:
        for keypoint in instance["keypoints"]:
            assert keypoint["guarantee"]["n"] == summary["labeled_per_keypoint"][keypoint["name"]]
    assert used_version(server, first_image)["calibration"]["version"] == previous

    refused = server.client.post(
        f"/v1/admin/calibrations/{version}/activate", json={"reason": "new batch"}, headers=server.admin
    )
    problem = assert_problem(refused, 409, "activation refused", "force")
    assert problem["comparison"]["against"] == previous and not problem["comparison"]["allowed"]
    assert active(server) == previous
    entry = activate(server, version, "new batch", force=True)
    assert (entry["version"], entry["who"], entry["reason"]) == (version, "admin", "new batch")
    assert active(server) == version
    assert used_version(server, first_image)["calibration"]["version"] == version
    assert used_version(server, first_image) == pinned

    listed = server.client.get("/v1/admin/calibrations", headers=server.admin).json()
    assert listed["active_version"] == version
    assert [v["version"] for v in listed["versions"] if v["active"]] == [version]

    rollback = activate(server, previous, "roll back")
    assert rollback["version"] == previous and rollback["seq"] > entry["seq"]
    assert active(server) == previous
    assert used_version(server, first_image)["calibration"]["version"] == previous
    assert server.versions() == [*before, version]  # rollback loses nothing

    log = server.client.get("/v1/admin/activations", headers=server.admin).json()
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
    server: LiveServer, samples_dir: Path, coco: dict, first_image
) -> None:
    parent = active(server)
    parent_detail = detail(server, parent)
    body = batch_zip(samples_dir, coco, images=3)
    batch_count = count_instances(coco, images=3)

    job = server.calibrate(body, append_to=parent, activate=True, note="appended")
    version = job["result"]["version"]
    assert job["result"] == result(version, parent_detail["instances"] + batch_count, True, batch_count)
    assert job["total"] == job["done"] == batch_count  # only the batch is scored
    assert active(server) == version
    assert used_version(server, first_image)["calibration"]["version"] == version

    child = detail(server, version)
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

    log = server.client.get("/v1/admin/activations", headers=server.admin).json()["activations"]
    assert log[-1]["version"] == version and log[-1]["reason"] == "activated on creation"
    activate(server, parent, "restore")  # leave the active version as found


def test_version_detail_reports_thresholds(server: LiveServer, manifest: dict) -> None:
    version = active(server)
    body = detail(server, version)
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


def test_missing_version_and_job_are_404(server: LiveServer) -> None:
    missing = max(server.versions()) + 100
    assert_problem(server.client.get(f"/v1/admin/calibrations/{missing}", headers=server.admin), 404)
    response = server.client.post(
        f"/v1/admin/calibrations/{missing}/activate", json={"reason": "x"}, headers=server.admin
    )
    assert_problem(response, 404, str(missing))
    assert_problem(server.client.get("/v1/admin/jobs/nope", headers=server.admin), 404)


@pytest.mark.parametrize("version", ["0", "-1", str(2**31), str(2**70), "one"])
def test_out_of_range_version_numbers_are_422(server: LiveServer, version: str) -> None:
    """Not 500: the store keeps version numbers as 32-bit integers >= 1."""
    versions = server.versions()
    assert_problem(
        server.client.get(f"/v1/admin/calibrations/{version}", headers=server.admin), 422, "version"
    )
    response = server.client.post(
        f"/v1/admin/calibrations/{version}/activate", json={"reason": "x"}, headers=server.admin
    )
    assert_problem(response, 422, "version")
    assert server.versions() == versions


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
def test_admin_needs_the_bearer_token(server: LiveServer, method: str, path: str, authorization) -> None:
    headers = {"Content-Type": "application/zip"}
    if authorization is not None:
        headers["Authorization"] = authorization
    versions = server.versions()
    response = server.client.request(method, path, headers=headers, content=b"PK")
    assert_problem(response, 401, "Bearer")
    assert response.headers["www-authenticate"] == "Bearer"
    assert server.versions() == versions


@pytest.fixture(scope="module")
def no_admin_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    with LiveServer(tmp_path_factory.mktemp("no-admin") / "data") as live:
        yield live


@pytest.mark.parametrize(("method", "path"), ADMIN_ROUTES)
def test_admin_is_disabled_without_a_configured_token(
    no_admin_server: LiveServer, method: str, path: str, first_image
) -> None:
    for headers in ({}, {"Authorization": f"Bearer {ADMIN_TOKEN}"}):
        response = no_admin_server.client.request(method, path, headers=headers, content=b"PK")
        assert_problem(response, 403, "CKS_ADMIN_TOKEN", "CKS_ADMIN_TOKENS_FILE")
    assert used_version(no_admin_server, first_image)["calibration"]["version"] == 1  # predict still works
