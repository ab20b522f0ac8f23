"""No admin action can silently void the guarantee: repeats refused, small batches held back
from activation unless forced with a reason, calibration boxes under the predict rule, every
admin action in the audit trail under the operator's name, and the store said out loud."""

from __future__ import annotations

import copy
import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path, PurePosixPath

import pytest

from tests.api.in_process import InProcess
from tests.samples import batch_zip, build_zip, count_instances
from tests.service_calls import ADMIN_TOKEN, assert_problem, wait_until

OPERATORS = {"alice": "alice-token-0123456789", "bob": "bob-token-9876543210"}


@pytest.fixture(scope="module")
def named_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[InProcess]:
    """A service with two named operators (a tokens file) and the single admin token."""
    root = tmp_path_factory.mktemp("operators")
    tokens = root / "tokens"
    tokens.write_text("# name:token\n" + "".join(f"{n}:{t}\n" for n, t in OPERATORS.items()))
    with InProcess(root / "data", admin_token=ADMIN_TOKEN, admin_tokens_file=tokens) as live:
        yield live


def as_operator(name: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {OPERATORS[name]}"}


def audit(api: InProcess, **params: object) -> list[dict]:
    response = api.client.get("/v1/admin/audit", params=params, headers=api.admin)
    assert response.status_code == 200, response.text
    return response.json()["entries"]


def upload(api: InProcess, body: bytes, operator: str = "alice", **params: object):
    params = {k: (str(v).lower() if isinstance(v, bool) else v) for k, v in params.items()}
    headers = {**as_operator(operator), "Content-Type": "application/zip"}
    return api.client.post("/v1/admin/calibrations", content=body, params=params, headers=headers)


def calibrate(api: InProcess, body: bytes, operator: str = "alice", **params: object) -> dict:
    response = upload(api, body, operator, **params)
    assert response.status_code == 202, response.text
    job = api.wait_job(response.json()["id"])
    assert job["state"] == "succeeded", job
    return job


def first_images(coco: dict, start: int, stop: int) -> dict:
    """The COCO document restricted to images[start:stop]."""
    doc = copy.deepcopy(coco)
    doc["images"] = doc["images"][start:stop]
    kept = {image["id"] for image in doc["images"]}
    doc["annotations"] = [a for a in doc["annotations"] if a["image_id"] in kept]
    return doc


def zip_of(samples_dir: Path, doc: dict) -> bytes:
    files = {image["file_name"]: (samples_dir / image["file_name"]).read_bytes() for image in doc["images"]}
    return build_zip(doc, files)


# ---------------------------------------------------------------- repeats


def test_the_same_zip_appended_twice_is_refused(
    named_server: InProcess, samples_dir: Path, coco: dict
) -> None:
    body = batch_zip(samples_dir, coco, images=3)
    version = calibrate(named_server, body)["version"]
    versions = named_server.versions()
    problem = assert_problem(upload(named_server, body, append_to=version), 409, "already counted", "dedupe")
    total = count_instances(coco, images=3)
    assert problem["duplicates"] == total
    assert f"{total} of {total} instances" in problem["detail"] and "the same batch" in problem["errors"][0]
    assert named_server.versions() == versions, "a refused upload stored something"
    entry = audit(named_server, limit=1)[0]
    assert (entry["action"], entry["outcome"], entry["who"]) == ("upload", "refused", "alice")
    assert entry["details"]["status"] == 409


def test_overlapping_batch_is_refused_or_deduplicated(
    named_server: InProcess, samples_dir: Path, coco: dict
) -> None:
    first = calibrate(named_server, zip_of(samples_dir, first_images(coco, 1, 3)))["version"]
    overlap = zip_of(samples_dir, first_images(coco, 2, 6))  # image 2 is in both
    repeated = len(first_images(coco, 2, 3)["annotations"])
    new = len(first_images(coco, 3, 6)["annotations"])
    problem = assert_problem(upload(named_server, overlap, append_to=first), 409, "already in version")
    assert problem["duplicates"] == repeated and len(problem["errors"]) == repeated

    job = calibrate(named_server, overlap, append_to=first, dedupe=True)
    assert job["result"]["duplicates_dropped"] == repeated and job["result"]["added"] == new
    assert job["total"] == new


def test_an_image_repeated_inside_a_batch_is_refused(
    named_server: InProcess, samples_dir: Path, coco: dict
) -> None:
    doc = first_images(coco, 0, 2)
    files = {image["file_name"]: (samples_dir / image["file_name"]).read_bytes() for image in doc["images"]}
    image = doc["images"][0]
    copy_name = str(PurePosixPath(image["file_name"]).with_name("copy.jpg"))
    files[copy_name] = files[image["file_name"]]
    doc["images"].append({**image, "id": 999, "file_name": copy_name})
    copies = [
        {**a, "id": 10_000 + i, "image_id": 999}
        for i, a in enumerate(doc["annotations"])
        if a["image_id"] == image["id"]
    ]
    doc["annotations"].extend(copies)
    problem = assert_problem(upload(named_server, build_zip(doc, files)), 409, f"repeats image {image['id']}")
    assert problem["duplicates"] == len(copies)


def test_identical_batches_sent_at_once_make_one_version(
    named_server: InProcess, samples_dir: Path, coco: dict
) -> None:
    """The second is accepted while the first is being scored (jobs run one at a time), or refused
    at once if the first was quicker: never two equal versions."""
    body = zip_of(samples_dir, first_images(coco, 9, 12))
    versions = named_server.versions()
    answers = [upload(named_server, body, name=f"twin {i}") for i in (1, 2)]
    assert answers[0].status_code == 202, answers[0].text
    first = named_server.wait_job(answers[0].json()["id"])
    assert first["state"] == "succeeded", first
    if answers[1].status_code == 202:
        twin = named_server.wait_job(answers[1].json()["id"])
        assert (
            twin["state"] == "failed"
            and f"equal to calibration version {first['version']}" in twin["errors"][0]
        )
    else:
        assert_problem(answers[1], 409, f"version {first['version']}")
    assert named_server.versions() == [*versions, first["version"]]


def test_identical_batches_are_refused_unless_allowed_with_a_reason(
    named_server: InProcess, samples_dir: Path, coco: dict
) -> None:
    body = zip_of(samples_dir, first_images(coco, 6, 9))
    first = calibrate(named_server, body, name="first")["version"]
    versions = named_server.versions()
    for copy_number in (2, 3, 4):  # the same content, also under another name and zip
        again = body if copy_number < 4 else zip_of(samples_dir, first_images(coco, 6, 9)) + b""
        problem = assert_problem(
            upload(named_server, again, "bob", name=f"copy {copy_number}"), 409, f"version {first}"
        )
        assert problem["duplicate_of"] == first and "allow_duplicate" in problem["detail"]
        entry = audit(named_server, limit=1)[0]
        assert (entry["action"], entry["outcome"], entry["who"]) == ("upload", "refused", "bob")
        assert entry["details"]["status"] == 409
    assert named_server.versions() == versions
    assert_problem(upload(named_server, body, allow_duplicate=True), 422, "allow_duplicate needs a reason")

    job = calibrate(named_server, body, "bob", allow_duplicate=True, reason="a second copy for the demo")
    accepted = next(e for e in audit(named_server) if e["action"] == "upload" and e["outcome"] == "accepted")
    assert accepted["details"]["job"] == job["id"] and accepted["who"] == "bob"
    assert accepted["details"]["duplicate_of"] == first
    assert accepted["details"]["why"] == "a second copy for the demo"
    assert named_server.versions() == [*versions, job["result"]["version"]]
    other_strata = calibrate(named_server, body, stratify="none")  # another version: no strata
    assert other_strata["result"]["version"] not in versions


# ---------------------------------------------------------------- activation guardrails


def test_a_small_batch_needs_force_and_a_reason_and_is_audited(
    named_server: InProcess, samples_dir: Path, coco: dict
) -> None:
    active = named_server.client.get("/readyz").json()["active_calibration"]
    job = calibrate(named_server, batch_zip(samples_dir, coco), "bob", activate=True)
    version = job["result"]["version"]
    assert job["result"]["activated"] is False and job["result"]["activation_problems"]
    assert named_server.client.get("/readyz").json()["active_calibration"] == active
    # one line per keypoint, naming every rule it breaks (here the floor and half the active n)
    problems = job["result"]["activation_problems"]
    named = [problem.split("'")[1] for problem in problems]
    assert len(named) == len(set(named)), problems
    duck_kp0 = next(problem for problem in problems if problem.startswith("keypoint 'duck_kp0': n = "))
    bundled = named_server.client.get("/v1/admin/calibrations/1", headers=as_operator("bob")).json()
    half = f"below half of the active version's {bundled['labeled_per_keypoint']['duck_kp0']}"
    assert "below the floor of 100" in duck_kp0 and half in duck_kp0

    dry = named_server.client.get(f"/v1/admin/calibrations/{version}/compare", headers=as_operator("bob"))
    assert dry.status_code == 200, dry.text
    comparison = dry.json()
    assert comparison["against"] == active and not comparison["allowed"]
    assert comparison["min_instances"] == 100
    duck = next(k for k in comparison["keypoints"] if k["keypoint"] == "duck_kp0")
    assert duck["n_before"] > 100 > duck["n_after"] > 0
    assert duck["smallest_bounded_epsilon_after"] == pytest.approx(1 / (duck["n_after"] + 1))
    assert 0 <= duck["active_coverage_of_candidate"] <= 1 and duck["set_area_ratio"] > 0

    itself = named_server.client.get(
        f"/v1/admin/calibrations/{version}/compare",
        params={"against": version, "nonconformity": "var", "epsilon": 0.2},
        headers=as_operator("bob"),
    ).json()
    assert (itself["against"], itself["nonconformity"], itself["epsilon"]) == (version, "var", 0.2)
    assert all(k["n_before"] == k["n_after"] for k in itself["keypoints"])
    assert itself["median_set_area_ratio"] == 1.0

    url = f"/v1/admin/calibrations/{version}/activate"
    refused = named_server.client.post(url, json={"reason": "try"}, headers=as_operator("bob"))
    problem = assert_problem(refused, 409, "activation refused", "below the floor of 100")
    assert problem["comparison"] == comparison
    no_reason = named_server.client.post(url, json={"force": True}, headers=as_operator("bob"))
    assert_problem(no_reason, 422, "force=true needs a reason")
    assert named_server.client.get("/readyz").json()["active_calibration"] == active

    body = {"force": True, "reason": "lab test"}
    forced = named_server.client.post(url, json=body, headers=as_operator("bob"))
    assert forced.status_code == 200, forced.text
    assert (forced.json()["who"], forced.json()["reason"]) == ("bob", "lab test")
    assert named_server.client.get("/readyz").json()["active_calibration"] == version

    entries = audit(named_server, limit=4)
    assert [(e["action"], e["outcome"], e["who"]) for e in entries[:2]] == [
        ("activation", "forced", "bob"),
        ("activation", "refused", "bob"),
    ]
    assert entries[0]["reason"] == "lab test" and entries[0]["previous_version"] == active
    assert entries[0]["client"] == "127.0.0.1" and entries[0]["details"]["problems"]

    rollback = named_server.client.post(
        f"/v1/admin/calibrations/{active}/activate", json={"reason": "restore"}, headers=as_operator("alice")
    )
    assert rollback.status_code == 200, rollback.text  # more instances: allowed without force
    entry = audit(named_server, limit=1)[0]
    assert (entry["action"], entry["outcome"], entry["who"], entry["version"]) == (
        "rollback",
        "activated",
        "alice",
        active,
    )


def test_force_without_a_reason_is_refused_before_the_upload_is_read(
    named_server: InProcess, samples_dir: Path, coco: dict
) -> None:
    response = upload(named_server, batch_zip(samples_dir, coco, images=1), activate=True, force=True)
    assert_problem(response, 422, "force needs a reason")


# ---------------------------------------------------------------- the box rule in calibration


@pytest.mark.parametrize(("bbox", "which"), [([100, 100, 1e-6, 1e-6], 0), ([630, 10, 50, 50], 1)])
def test_boxes_that_predict_refuses_are_rejected_with_reasons(
    named_server: InProcess, samples_dir: Path, coco: dict, bbox: list[float], which: int
) -> None:
    doc = first_images(coco, 0, 3)  # a different annotation each: versions of the same content are refused
    doc["annotations"][which]["bbox"] = bbox
    body = zip_of(samples_dir, doc)
    versions = named_server.versions()
    problem = assert_problem(upload(named_server, body), 422, "were rejected", "max_rejected_share", "bbox")
    assert problem["rejected"] == 1 and problem["instances"] == len(doc["annotations"])
    assert named_server.versions() == versions

    job = calibrate(named_server, body, max_rejected_share=0.5)
    assert job["result"]["rejected"] == 1 and job["total"] == len(doc["annotations"]) - 1
    assert f"annotation {doc['annotations'][which]['id']}" in job["result"]["rejections"][0]


def test_an_image_that_does_not_decode_is_rejected_in_the_job(
    named_server: InProcess, samples_dir: Path, coco: dict
) -> None:
    doc = first_images(coco, 0, 3)
    files = {image["file_name"]: (samples_dir / image["file_name"]).read_bytes() for image in doc["images"]}
    broken = doc["images"][1]
    data = files[broken["file_name"]]
    files[broken["file_name"]] = data[: len(data) // 2]  # truncated: its header is intact
    on_broken = sum(1 for a in doc["annotations"] if a["image_id"] == broken["id"])
    versions = named_server.versions()

    response = upload(named_server, build_zip(doc, files))
    assert response.status_code == 202, response.text
    job = named_server.wait_job(response.json()["id"])
    assert job["state"] == "failed" and "were rejected" in job["errors"][0], job
    assert any(broken["file_name"] in e and "cannot be decoded" in e for e in job["errors"]), job
    assert named_server.versions() == versions

    job = calibrate(named_server, build_zip(doc, files), max_rejected_share=0.9)
    assert job["result"]["rejected"] == on_broken
    assert job["result"]["added"] == len(doc["annotations"]) - on_broken


# ---------------------------------------------------------------- operators, audit trail, store


def test_operators_are_named_and_the_single_token_is_admin(named_server: InProcess) -> None:
    for headers in (as_operator("alice"), as_operator("bob"), named_server.admin):
        assert named_server.client.get("/v1/admin/store", headers=headers).status_code == 200
    wrong = {"Authorization": "Bearer alice-token-0123456788"}
    assert_problem(named_server.client.get("/v1/admin/store", headers=wrong), 401)


@pytest.mark.slow
def test_an_activation_refused_for_a_store_lock_timeout_is_audited(named_server: InProcess) -> None:
    """Another writer holds SQLite's lock past the busy timeout (CKS_STORE_TIMEOUT_SECONDS, 1.5 s,
    not SQLite's 30 s): the activation is refused (503), and its entry lands once the store can
    take it."""
    locker = sqlite3.connect(named_server.data_dir / "calibrations.db", isolation_level=None)
    locker.execute("BEGIN IMMEDIATE")
    began = time.monotonic()
    try:
        refused = named_server.client.post(
            "/v1/admin/calibrations/1/activate", json={"reason": "while locked"}, headers=as_operator("bob")
        )
        waited = time.monotonic() - began
    finally:
        locker.execute("ROLLBACK")
        locker.close()
    assert_problem(refused, 503, "database is locked")
    assert waited < 15, f"the lock wait was not bounded by CKS_STORE_TIMEOUT_SECONDS: {waited:.1f} s"

    def refusal() -> dict:
        return next((e for e in audit(named_server) if e["reason"] == "while locked"), {})

    wait_until(lambda: refusal() != {}, "the refusal's entry is stored")
    entry = refusal()
    assert (entry["action"], entry["outcome"], entry["who"], entry["version"]) == (
        "activation",
        "refused",
        "bob",
        1,
    )
    assert entry["details"]["status"] == 503 and "locked" in entry["details"]["detail"], entry


def test_the_audit_trail_pages_and_cannot_be_edited(named_server: InProcess) -> None:
    everything = audit(named_server, limit=1000)
    assert len(everything) >= 4
    seqs = [e["seq"] for e in everything]
    assert seqs == sorted(seqs, reverse=True)
    first = named_server.client.get("/v1/admin/audit", params={"limit": 2}, headers=named_server.admin).json()
    second = audit(named_server, limit=2, before=first["next_before"])
    assert [e["seq"] for e in first["entries"] + second] == seqs[:4]
    for method in ("PUT", "PATCH", "DELETE"):
        response = named_server.client.request(method, "/v1/admin/audit", headers=named_server.admin)
        assert_problem(response, 405)
    assert audit(named_server, limit=1000)[-len(everything) :] == everything


def test_the_store_is_said_out_loud(named_server: InProcess) -> None:
    response = named_server.client.get("/v1/admin/store", headers=named_server.admin)
    assert response.status_code == 200, response.text
    body = response.json()
    data_dir = named_server.data_dir.resolve()
    assert body["kind"] == "sqlite" and body["location"] == str(data_dir / "calibrations.db")
    assert body["data_dir"] == str(data_dir) and len(body["model_hash"]) == 64
    log = named_server.log()
    assert f"calibration store: sqlite at {data_dir / 'calibrations.db'}" in log
    assert body["model_hash"] in log and "admin operators: admin, alice, bob" in log
