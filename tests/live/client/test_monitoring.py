"""Coverage audits and drift through the client, against a real server: the bundled samples
audited (a folder zipped by the client, the job waited for, the stored audit read), listed in
pages, refusals typed; the drift of the live features after predictions."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from keypoint_client import (
    AsyncKeypointClient,
    Conflict,
    CoverageAudit,
    Drift,
    InvalidInput,
    Job,
    KeypointClient,
    NotFound,
    Unauthorized,
)
from keypoint_client.archive import zip_coco_folder

from tests.live.server import LiveServer
from tests.predict_client import instances_of
from tests.samples import Sample, count_instances, samples_by_image
from tests.service_calls import ADMIN_TOKEN


@pytest.fixture(scope="module")
def samples_audit(admin: KeypointClient, samples_dir: Path) -> tuple[CoverageAudit, list[Job]]:
    """The bundled samples audited against the active version (they never calibrated it)."""
    seen: list[Job] = []
    audit = admin.run_audit(samples_dir, epsilon=[0.2, 0.1], note="from the client", progress=seen.append)
    return audit, seen


def test_an_audit_is_run_and_read_typed(
    server: LiveServer, admin: KeypointClient, samples_audit, coco: dict
) -> None:
    audit, seen = samples_audit
    total = count_instances(coco)
    assert seen[-1].state == "succeeded" and seen[-1].kind == "audit" and seen[-1].done == total
    assert seen[-1].result["audit"] == audit.id
    assert (audit.version, audit.report.version, audit.instances) == (1, 1, total)
    report = audit.report
    assert report.batch.note == "from the client" and report.batch.annotations == total
    assert {section.epsilon for section in report.sections} == {0.1, 0.2}
    assert audit.passed == report.passed == (not report.flagged) and audit.flagged == len(report.flagged)
    for section in report.sections:
        figure = section.overall
        assert section.scope in ("keypoint", "object") and figure.m > 0
        assert figure.coverage == pytest.approx(figure.covered / figure.m)
        assert figure.promised == pytest.approx(1 - section.epsilon)
    # The typed audit is the API's JSON, field for field.
    raw = server.client.get(f"/v1/admin/audits/{audit.id}", headers=server.admin)
    assert raw.status_code == 200 and CoverageAudit.model_validate_json(raw.content) == audit
    assert audit.to_dict() == raw.json()
    assert admin.coverage_audit(seen[-1]) == audit  # by the job that made it


def test_audits_are_listed_in_pages_and_asyncio_runs_one(
    server: LiveServer, admin: KeypointClient, samples_audit, samples_dir: Path, tmp_path: Path
) -> None:
    first, _ = samples_audit
    zip_coco_folder(samples_dir, tmp_path / "samples.zip")

    async def audit_again() -> CoverageAudit:
        async with AsyncKeypointClient(server.url, token=ADMIN_TOKEN) as client:
            return await client.run_audit(tmp_path / "samples.zip", epsilon=[0.1], version=1)

    second = asyncio.run(audit_again())
    assert second.id > first.id and {s.epsilon for s in second.report.sections} == {0.1}
    listed = admin.audits()
    assert [a.id for a in listed.audits][:2] == [second.id, first.id]
    assert listed.model_hash == admin.model().hash and listed.next_before is None
    page = admin.audits(limit=1)
    assert [a.id for a in page.audits] == [second.id] and page.next_before == second.id
    older = admin.audits(before=page.next_before, limit=1)
    assert [a.id for a in older.audits] == [first.id]
    assert older.audits[0] == next(a for a in listed.audits if a.id == first.id)


def test_audit_refusals_are_typed(
    server: LiveServer, admin: KeypointClient, samples_audit, samples_dir: Path
) -> None:
    with pytest.raises(NotFound, match="does not exist"):
        admin.start_audit(samples_dir, version=999)
    with pytest.raises(InvalidInput, match="epsilon"):
        admin.start_audit(samples_dir, epsilon=[1.5])
    with pytest.raises(InvalidInput, match="max_rejected_share"):
        admin.start_audit(samples_dir, max_rejected_share=2.0)
    with pytest.raises(NotFound, match="GET /v1/admin/audits lists them"):
        admin.coverage_audit(10**9)
    calibration = admin.calibrate(samples_dir, name="samples")  # a version calibrated with them
    with pytest.raises(ValueError, match="has made no coverage audit"):
        admin.coverage_audit(calibration)
    with pytest.raises(Conflict, match="dedupe"):
        admin.start_audit(samples_dir, version=calibration.version)
    with KeypointClient(server.url, token="wrong-token") as intruder, pytest.raises(Unauthorized):
        intruder.audits()


def test_drift_after_predictions(server: LiveServer, admin: KeypointClient, samples: list[Sample]) -> None:
    before = admin.drift()
    with KeypointClient(server.url) as client:
        for path, group in samples_by_image(samples).items():
            client.predict(path, instances_of(group))
    drift = admin.drift()
    assert isinstance(drift, Drift) and drift.recorded > before.recorded
    assert drift.reference_available and drift.reference_version == admin.versions().active_version
    assert drift.reason is None and drift.statistic in ("sequential", "ks", "psi")
    keypoints = {(k.object, k.keypoint) for k in drift.keypoints}
    assert len(keypoints) == len(drift.keypoints)
    assert {k.object for k in drift.keypoints} == set(admin.model().object_names)
    for keypoint in drift.keypoints:
        assert keypoint.features and all(test.reference_n > 0 for test in keypoint.features.values())
    assert drift.alarm == any(o.alarm for o in drift.objects)
    raw = server.client.get("/v1/admin/drift", headers=server.admin).json()
    assert set(drift.to_dict()) == set(raw) and set(Drift.model_fields) == set(raw)
    with KeypointClient(server.url) as anonymous, pytest.raises(Unauthorized):
        anonymous.drift()
