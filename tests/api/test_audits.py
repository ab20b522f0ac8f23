"""Coverage audits end to end in process (the ASGI app): the bundled samples agree with the bundled
calibration, the same images with labels shifted by a few pixels are flagged, audits are
stored, listed, published as metrics and never change a calibration, and bad uploads get 4xx."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.api.in_process import InProcess
from tests.predict_client import contains, instances_of, predict_ok
from tests.samples import Sample, batch_zip, count_instances, samples_by_image
from tests.service_calls import ADMIN_TOKEN, assert_problem, wait_until

FUNCTIONS = {"peak", "var", "cov"}
SHIFT_PX = 5


def shifted(pixels: float):
    """Move every labeled keypoint ``pixels`` to the right (the labels of another annotator)."""

    def mutate(doc: dict, files: dict[str, bytes]) -> None:
        for annotation in doc["annotations"]:
            flat = annotation["keypoints"]
            for i in range(0, len(flat), 3):
                if flat[i + 2] > 0:
                    flat[i] += pixels

    return mutate


def start_audit(api: InProcess, body: bytes, content_type: str = "application/zip", **params):
    params = {k: (str(v).lower() if isinstance(v, bool) else v) for k, v in params.items()}
    return api.client.post(
        "/v1/admin/audits",
        content=body,
        params=params,
        headers={**api.admin, "Content-Type": content_type},
    )


def run_audit(api: InProcess, body: bytes, **params) -> dict:
    """Audit a batch, wait for the job, return the stored audit."""
    response = start_audit(api, body, **params)
    assert response.status_code == 202, response.text
    job = response.json()
    assert job["kind"] == "audit" and response.headers["location"] == f"/v1/admin/jobs/{job['id']}"
    job = api.wait_job(job["id"])
    assert job["state"] == "succeeded", job
    audit = api.client.get(f"/v1/admin/audits/{job['result']['audit']}", headers=api.admin)
    assert audit.status_code == 200, audit.text
    return audit.json()


def exact_figures(report: dict) -> list[dict]:
    """The figures Theorem 1 speaks about exactly: keypoints (keypoint scope), objects (object scope)."""
    return [
        figure
        for section in report["sections"]
        for figure in (section["keypoints"] if section["scope"] == "keypoint" else section["objects"])
    ]


@pytest.fixture(scope="module")
def calibrations(api: InProcess) -> Iterator[tuple]:
    """The versions and activation log before any audit, to check after them."""
    before = (
        api.client.get("/v1/admin/calibrations", headers=api.admin).json(),
        api.client.get("/v1/admin/activations", headers=api.admin).json(),
    )
    yield before


@pytest.fixture(scope="module")
def samples_audit(api: InProcess, calibrations: tuple, samples_dir: Path, coco: dict) -> dict:
    return run_audit(api, batch_zip(samples_dir, coco), name="samples", note="bundled samples")


@pytest.fixture(scope="module")
def shifted_audit(api: InProcess, samples_audit: dict, samples_dir: Path, coco: dict) -> dict:
    return run_audit(api, batch_zip(samples_dir, coco, mutate=shifted(SHIFT_PX)), name="shifted")


def test_the_bundled_samples_are_covered_within_their_bands(samples_audit: dict, coco: dict) -> None:
    report = samples_audit["report"]
    active = report["version"]
    assert samples_audit["version"] == active and samples_audit["instances"] == count_instances(coco)
    assert report["passed"] and report["flagged"] == [] and samples_audit["flagged"] == 0
    assert {(s["nonconformity"], s["epsilon"], s["scope"]) for s in report["sections"]} == {
        (kind, epsilon, scope)
        for kind in FUNCTIONS
        for epsilon in (0.05, 0.1, 0.2)
        for scope in ("keypoint", "object")
    }
    pooled = [section["overall"] for section in report["sections"]]
    pooled += [f for s in report["sections"] if s["scope"] == "keypoint" for f in s["objects"]]
    for figure in pooled:  # the 12 samples are easy: some pooled figures lie above their band, none below
        low, high = figure["band"]
        assert figure["in_band"] == (low <= figure["coverage"] <= high) and not figure["flagged"]
        assert figure["coverage"] >= low, figure
    exact = exact_figures(report)
    assert report["tests"] == len([f for f in exact if f["m"] > 0]) + len(pooled)
    assert sum(f["in_band"] for f in exact) / len(exact) >= 0.95
    for figure in exact:
        assert figure["n"] > 0 and figure["rank"] == int((figure["n"] + 1) * (1 - figure["promised"]) + 1e-9)
        assert figure["adjusted_p_value"] >= figure["p_value"] and not figure["flagged"]
    assert report["batch"]["name"] == "samples" and report["batch"]["note"] == "bundled samples"
    assert report["advice"].startswith(f"Version {active} holds on this batch")


def test_labels_shifted_by_a_few_pixels_are_flagged(shifted_audit: dict) -> None:
    report = shifted_audit["report"]
    assert not report["passed"] and shifted_audit["flagged"] == len(report["flagged"]) > 0
    for figure in report["flagged"]:
        assert figure["p_value"] <= figure["adjusted_p_value"] <= report["family_alpha"]
        assert figure["coverage"] < figure["promised"]
    flagged_keypoints = {f["keypoint"] for f in report["flagged"] if f["scope"] == "keypoint"}
    assert len(flagged_keypoints) >= 5
    needed = [int(n) for n in re.findall(r"(\d+) at epsilon", report["advice"])]
    assert "Recalibrate with labeled images like the audited ones" in report["advice"]
    assert len(needed) == 3 and all(n >= 19 for n in needed)  # at least 1/(n+1) <= 0.05


@pytest.mark.parametrize("kind", ["peak", "cov"])
@pytest.mark.parametrize("scope", ["keypoint", "object"])
def test_covered_means_inside_the_sets_that_predict_returns(
    api: InProcess, shifted_audit: dict, samples: list[Sample], kind: str, scope: str
) -> None:
    """The audit's count is the number of true keypoints inside the served sets (the score
    inequality and the set are one), counted here from /v1/predict on the shifted labels."""
    section = next(
        s
        for s in shifted_audit["report"]["sections"]
        if (s["nonconformity"], s["epsilon"], s["scope"]) == (kind, 0.1, scope)
    )
    inside: dict[str, list[bool]] = {}
    for path, group in samples_by_image(samples).items():
        parameters = {
            "instances": instances_of(group),
            "nonconformity": kind,
            "epsilon": 0.1,
            "coverage": scope,
        }
        body = predict_ok(api.client, path.read_bytes(), parameters)
        for sample, instance in zip(group, body["instances"], strict=True):
            labeled = [
                (x, y, k) for (x, y, v), k in zip(sample.keypoints, instance["keypoints"], strict=True) if v
            ]
            hits = [contains(keypoint["set"], (x + SHIFT_PX, y), slack=1e-6) for x, y, keypoint in labeled]
            if scope == "keypoint":
                for (_, _, keypoint), hit in zip(labeled, hits, strict=True):
                    inside.setdefault(keypoint["name"], []).append(hit)
            elif len(hits) == len(sample.keypoints):  # object scope counts fully labeled instances
                inside.setdefault(sample.object, []).append(all(hits))
    figures = section["keypoints"] if scope == "keypoint" else section["objects"]
    for figure in figures:
        counted = inside.get(figure["keypoint" if scope == "keypoint" else "object"], [])
        assert (figure["m"], figure["covered"]) == (len(counted), sum(counted)), figure


def test_an_audit_never_changes_a_calibration(
    api: InProcess, calibrations: tuple, samples_audit: dict, shifted_audit: dict
) -> None:
    versions, activations = calibrations
    assert api.client.get("/v1/admin/calibrations", headers=api.admin).json() == versions
    assert api.client.get("/v1/admin/activations", headers=api.admin).json() == activations


def test_audits_are_listed_newest_first_in_pages(api: InProcess, samples_audit: dict, shifted_audit: dict):
    listed = api.client.get("/v1/admin/audits", headers=api.admin).json()
    ids = [audit["id"] for audit in listed["audits"]]
    assert ids == sorted(ids, reverse=True) and {samples_audit["id"], shifted_audit["id"]} <= set(ids)
    first = api.client.get("/v1/admin/audits", params={"limit": 1}, headers=api.admin).json()
    assert [a["id"] for a in first["audits"]] == ids[:1] and first["next_before"] == ids[0]
    rest = api.client.get("/v1/admin/audits", params={"before": ids[0]}, headers=api.admin).json()
    assert [a["id"] for a in rest["audits"]] == ids[1:]
    summary = next(a for a in listed["audits"] if a["id"] == shifted_audit["id"])
    assert summary == {k: v for k, v in shifted_audit.items() if k != "report"}
    assert_problem(api.client.get("/v1/admin/audits/999999", headers=api.admin), 404, "no coverage audit")
    assert api.client.get("/v1/admin/audits").status_code == 401
    assert api.client.delete(f"/v1/admin/audits/{ids[0]}", headers=api.admin).status_code == 405
    jobs = api.client.get("/v1/admin/audit", headers=api.admin).json()["entries"]
    job_id = next(e["details"]["job"] for e in jobs if e["action"] == "audit" and e["outcome"] == "accepted")
    retried = api.client.post(f"/v1/admin/jobs/{job_id}/retry", headers=api.admin)
    assert_problem(retried, 409, "only calibration jobs are retried")


def test_the_latest_audit_is_in_the_metrics_of_every_replica(
    api: InProcess, shifted_audit: dict, tmp_path: Path
) -> None:
    latest = api.client.get("/v1/admin/audits", params={"limit": 1}, headers=api.admin).json()
    report = api.client.get(f"/v1/admin/audits/{latest['audits'][0]['id']}", headers=api.admin).json()
    flagged = report["report"]["flagged"][0] if report["report"]["flagged"] else None
    with InProcess(api.data_dir, admin_token=ADMIN_TOKEN) as replica:  # reads it from the store at start
        for live in (api, replica):
            text = live.client.get("/metrics").text
            assert f'cks_audit_latest_id{{version="{report["version"]}"}} {float(report["id"])}' in text
            overall = next(
                s
                for s in report["report"]["sections"]
                if (s["nonconformity"], s["epsilon"], s["scope"]) == ("cov", 0.1, "keypoint")
            )
            labels = 'epsilon="0.1",keypoint="",nonconformity="cov",object="",scope="keypoint"'
            assert _gauge(text, "cks_audit_coverage", labels) == pytest.approx(overall["overall"]["coverage"])
            assert _gauge(text, "cks_audit_band_low", labels) == pytest.approx(overall["overall"]["band"][0])
            if flagged is not None and flagged["scope"] == "keypoint":
                labels = (
                    f'epsilon="{flagged["epsilon"]:g}",keypoint="{flagged["keypoint"] or ""}",'
                    f'nonconformity="{flagged["nonconformity"]}",object="{flagged["object"] or ""}",'
                    'scope="keypoint"'
                )
                assert _gauge(text, "cks_audit_flagged", labels) == 1.0


def _gauge(text: str, name: str, labels: str) -> float:
    match = re.search(rf"^{name}{{{re.escape(labels)}}} (\S+)$", text, re.MULTILINE)
    assert match, f"{name}{{{labels}}} is not in the metrics"
    return float(match.group(1))


def test_a_named_version_is_audited_and_its_own_instances_are_refused(
    api: InProcess, samples_dir: Path, coco: dict, samples_audit: dict
) -> None:
    job = api.calibrate(batch_zip(samples_dir, coco, images=3), name="three-images")
    version = job["version"]
    body = batch_zip(samples_dir, coco)
    assert_problem(
        start_audit(api, body, version=version),
        409,
        f"version {version} was not calibrated with",
        "dedupe",
    )
    audit = run_audit(api, body, version=version, dedupe=True, epsilon=[0.2, 0.1])
    report = audit["report"]
    assert audit["version"] == report["version"] == version
    assert report["batch"]["duplicates_dropped"] == count_instances(coco, images=3)
    assert audit["instances"] == count_instances(coco) - count_instances(coco, images=3)
    assert {s["epsilon"] for s in report["sections"]} == {0.1, 0.2}
    latest = [(f'version="{version}"', f"{float(audit['id'])}")]

    def published() -> bool:  # the job reads succeeded once stored; its gauges follow a moment later
        metrics = api.client.get("/metrics").text
        return re.findall(r"^cks_audit_latest_id\{(.*)\} (\S+)$", metrics, re.MULTILINE) == latest

    wait_until(published, "the audit's gauges are published")
    metrics = api.client.get("/metrics").text  # the gauges are this audit's alone
    epsilons = set(re.findall(r'^cks_audit_coverage\{epsilon="([^"]+)"', metrics, re.MULTILINE))
    assert epsilons == {"0.1", "0.2"}


@pytest.mark.parametrize(
    "params, status, fragment",
    [
        ({"version": 999}, 404, "does not exist"),
        ({"version": 0}, 422, "version"),
        ({"epsilon": 1.5}, 422, "epsilon"),
        ({"epsilon": "often"}, 422, "epsilon"),
        ({"max_rejected_share": 2}, 422, "max_rejected_share"),
    ],
)
def test_bad_parameters_are_refused(
    api: InProcess, samples_dir: Path, coco: dict, params: dict, status: int, fragment: str
) -> None:
    response = start_audit(api, batch_zip(samples_dir, coco, images=1), **params)
    assert response.status_code == status, response.text
    assert fragment in response.text


def test_bad_uploads_are_refused(api: InProcess, samples_dir: Path, coco: dict) -> None:
    before = api.client.get("/v1/admin/audits", headers=api.admin).json()["audits"]
    assert_problem(start_audit(api, b"not a zip", content_type="text/plain"), 422, "zip")
    assert_problem(start_audit(api, b"not a zip"), 422, "zip")

    def unknown_object(doc: dict, files: dict) -> None:
        doc["categories"][0]["name"] = "spaceship"

    def bad_json(doc: dict, files: dict) -> None:
        doc["annotations"][0]["keypoints"] = "here"

    for mutate in (unknown_object, bad_json):
        response = start_audit(api, batch_zip(samples_dir, coco, images=2, mutate=mutate))
        assert response.status_code == 422, response.text
    headers = {"Content-Type": "application/zip", "Authorization": "Bearer wrong-token"}
    response = api.client.post(
        "/v1/admin/audits", content=batch_zip(samples_dir, coco, images=1), headers=headers
    )
    assert response.status_code == 401
    assert api.client.get("/v1/admin/audits", headers=api.admin).json()["audits"] == before
    assert api.upload_workspaces() == []
    trail = api.client.get("/v1/admin/audit", headers=api.admin).json()["entries"]
    assert any(e["action"] == "audit" and e["outcome"] == "refused" for e in trail), json.dumps(trail)[:500]
