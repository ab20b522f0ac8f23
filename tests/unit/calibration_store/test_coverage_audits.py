"""Coverage audits in the store: stored whole, listed newest first per model, paged, tied to an
existing version, written with their job's success in one transaction, and never changed."""

from __future__ import annotations

import hashlib
from datetime import UTC, datetime

import pytest

from calibration_store import (
    CalibrationStore,
    JobCompletion,
    JobFinished,
    JobRecord,
    NewCoverageAudit,
    VersionNotFound,
)
from tests.unit.calibration_store import rawdb
from tests.unit.calibration_store.factories import MODEL_A, MODEL_B, new_version, score_table

REPORT = {
    "passed": False,
    "flagged": [{"object": "mug", "keypoint": "mug_kp0", "p_value": 1e-9}],
    "levels": [0.05, 0.1, 0.2],
    "nested": {"band": [0.8, 0.95]},
}


def audit(version: int = 1, model_hash: str = MODEL_A, who: str = "alice", n: int = 52) -> NewCoverageAudit:
    digest = hashlib.sha256(f"{model_hash}{version}{who}".encode()).hexdigest()
    return NewCoverageAudit(
        model_hash=model_hash, version=version, who=who, batch_sha256=digest, n_instances=n, report=REPORT
    )


def test_an_audit_round_trips(store: CalibrationStore) -> None:
    store.create_version(new_version(), score_table(n=4))
    stored = store.create_coverage_audit(audit())
    assert stored.id >= 1 and stored.created_at is not None and stored.created_at.tzinfo is not None
    assert (stored.version, stored.who, stored.n_instances, dict(stored.report)) == (1, "alice", 52, REPORT)
    assert store.coverage_audit(MODEL_A, stored.id) == stored
    assert store.coverage_audit(MODEL_B, stored.id) is None
    assert store.coverage_audit(MODEL_A, stored.id + 1) is None


def test_audits_list_newest_first_per_model_in_pages(store: CalibrationStore) -> None:
    store.create_version(new_version(), score_table(n=4))
    store.create_version(new_version(model_hash=MODEL_B), score_table(n=4))
    ids = [store.create_coverage_audit(audit(who=f"op{i}")).id for i in range(5)]
    store.create_coverage_audit(audit(model_hash=MODEL_B))
    first = store.coverage_audits(MODEL_A, limit=3)
    assert [a.id for a in first] == ids[::-1][:3]
    rest = store.coverage_audits(MODEL_A, before=first[-1].id, limit=3)
    assert [a.id for a in rest] == ids[::-1][3:]
    assert store.coverage_audits(MODEL_A, before=rest[-1].id) == []


def test_an_audit_needs_an_existing_version(store: CalibrationStore) -> None:
    store.create_version(new_version(), score_table(n=4))
    with pytest.raises(VersionNotFound):
        store.create_coverage_audit(audit(version=2))
    assert store.coverage_audits(MODEL_A) == []


def test_an_audit_and_its_job_success_are_one_transaction(store: CalibrationStore) -> None:
    store.create_version(new_version(), score_table(n=4))
    now = datetime.now(UTC)
    store.create_job(JobRecord(id="audit-job", kind="audit", owner="test", created_at=now, heartbeat_at=now))
    stored = store.create_coverage_audit(audit(), job=JobCompletion("audit-job", {"passed": False}))
    job = store.get_job("audit-job")
    assert job.state == "succeeded" and job.result == {"passed": False, "audit": stored.id}
    with pytest.raises(JobFinished):  # a finished job refuses a second audit, which is not written
        store.create_coverage_audit(audit(who="bob"), job=JobCompletion("audit-job"))
    assert [a.id for a in store.coverage_audits(MODEL_A)] == [stored.id]


def test_the_database_refuses_to_edit_audits(store: CalibrationStore, store_url: str) -> None:
    store.create_version(new_version(), score_table(n=4))
    stored = store.create_coverage_audit(audit())
    for sql in ("UPDATE calib_coverage_audits SET report = '{}'", "DELETE FROM calib_coverage_audits"):
        with pytest.raises(Exception, match="immutable"):
            rawdb.query(store_url, sql)
    assert store.coverage_audit(MODEL_A, stored.id) == stored


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"batch_sha256": "xyz"}, "sha256"),
        ({"version": 0}, "version"),
        ({"n_instances": -1}, "instances"),
        ({"who": " "}, "who"),
        ({"report": {"bad": float("nan")}}, "JSON"),
    ],
)
def test_invalid_audits_are_refused_before_the_store(changes: dict, message: str) -> None:
    fields = {
        "model_hash": MODEL_A,
        "version": 1,
        "who": "alice",
        "batch_sha256": "0" * 64,
        "n_instances": 1,
        "report": {},
    } | changes
    with pytest.raises((ValueError, TypeError), match=message):
        NewCoverageAudit(**fields)
