"""Integrity features of the store: content hashes, a version written together with its
activation, its job's success and audit entries in one transaction, finished jobs that never
change, and the append-only audit trail."""

from __future__ import annotations

import hashlib
from datetime import UTC, datetime

import pytest

from calibration_store import (
    ActivationIntent,
    CalibrationStore,
    JobCompletion,
    JobExists,
    JobFinished,
    JobNotFound,
    JobRecord,
    NewAuditEntry,
    ObjectScores,
    ScoreTable,
    StoreError,
)
from tests.unit.calibration_store import rawdb
from tests.unit.calibration_store.factories import MODEL_A, MODEL_B, new_version, object_scores, score_table


def _digest(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def _hashed(block: ObjectScores) -> ObjectScores:
    refs = block.instance_refs
    return ObjectScores(
        block.object_name,
        block.keypoint_ids,
        refs,
        block.scores,
        image_hashes=tuple(_digest(f"image {ref}") for ref in refs),
        instance_hashes=tuple(_digest(f"instance {ref}") for ref in refs),
    )


def _job(store: CalibrationStore, job_id: str = "job-1") -> JobRecord:
    now = datetime.now(UTC)
    return store.create_job(
        JobRecord(
            id=job_id, kind="calibration", owner="host:1", created_at=now, heartbeat_at=now, state="running"
        )
    )


def _audit(action: str = "activation", outcome: str = "done", **fields: object) -> NewAuditEntry:
    return NewAuditEntry(model_hash=MODEL_A, who="alice", action=action, outcome=outcome, **fields)


def test_content_hashes_round_trip(store: CalibrationStore) -> None:
    table = ScoreTable(tuple(_hashed(block) for block in score_table(n=6).objects))
    info = store.create_version(new_version(), table)
    loaded = store.load_scores(MODEL_A, info.number)
    for got, want in zip(loaded.objects, table.objects, strict=True):
        assert got.has_hashes
        assert got.image_hashes == want.image_hashes
        assert got.instance_hashes == want.instance_hashes


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"image_hashes": ("ab",) * 3, "instance_hashes": (_digest("x"),) * 3}, "64 lowercase hex"),
        ({"image_hashes": (_digest("x"),) * 2, "instance_hashes": (_digest("x"),) * 2}, "2 digests for 3"),
        ({"image_hashes": (_digest("x"),) * 3}, "both"),
    ],
)
def test_content_hashes_are_validated(fields: dict, message: str) -> None:
    block = object_scores("mug", 3, [0, 1])
    with pytest.raises(ValueError, match=message):
        ObjectScores(block.object_name, block.keypoint_ids, block.instance_refs, block.scores, **fields)


def test_version_activation_job_and_audit_in_one_transaction(store: CalibrationStore) -> None:
    _job(store)
    info = store.create_version(
        new_version(),
        score_table(n=4),
        activation=ActivationIntent("alice", "first"),
        job=JobCompletion("job-1", {"instances": 6}),
        audit=[_audit("job", outcome="succeeded"), _audit("activation", reason="first")],
    )
    assert store.active_version(MODEL_A).version == info.number
    job = store.get_job("job-1")
    assert (job.state, job.version, dict(job.result)) == ("succeeded", 1, {"instances": 6, "version": 1})
    assert job.finished_at is not None
    entries = store.audit_log(MODEL_A)
    assert [(e.action, e.version) for e in entries] == [("activation", 1), ("job", 1)]  # newest first


def test_a_finished_job_refuses_its_version_and_nothing_is_written(store: CalibrationStore) -> None:
    _job(store)
    store.update_job("job-1", state="interrupted")
    with pytest.raises(JobFinished, match="interrupted"):
        store.create_version(
            new_version(),
            score_table(n=4),
            activation=ActivationIntent("alice"),
            job=JobCompletion("job-1"),
            audit=[_audit()],
        )
    assert store.list_versions(MODEL_A) == []
    assert store.active_version(MODEL_A) is None
    assert store.audit_log(MODEL_A) == []
    with pytest.raises(JobNotFound):
        store.create_version(new_version(), score_table(n=4), job=JobCompletion("no-such-job"))
    assert store.list_versions(MODEL_A) == []


def test_finished_jobs_never_change(store: CalibrationStore) -> None:
    _job(store)
    store.update_job("job-1", state="succeeded", result={"version": 3})
    with pytest.raises(JobFinished, match="succeeded"):
        store.update_job("job-1", state="running")
    with pytest.raises(JobFinished):
        store.update_job("job-1")  # not even a heartbeat
    assert store.get_job("job-1").state == "succeeded"


def test_activation_appends_its_audit_entry_atomically(store: CalibrationStore) -> None:
    store.create_version(new_version(), score_table(n=4))
    store.activate(MODEL_A, 1, "alice", "go", audit=[_audit(version=1, reason="go", client="10.0.0.1")])
    (entry,) = store.audit_log(MODEL_A)
    assert (entry.who, entry.version, entry.reason, entry.client) == ("alice", 1, "go", "10.0.0.1")
    assert entry.at is not None and entry.at.tzinfo is not None
    with pytest.raises(StoreError):
        store.activate(MODEL_A, 9, "alice", audit=[_audit(version=9)])
    assert len(store.audit_log(MODEL_A)) == 1  # the refused activation wrote no entry


def test_a_job_is_created_with_its_audit_entry_atomically(store: CalibrationStore) -> None:
    now = datetime.now(UTC)
    job = JobRecord(id="job-1", kind="calibration", owner="host:1", created_at=now, heartbeat_at=now)
    store.create_job(job, audit=[_audit("upload", "accepted", details={"job": "job-1"})])
    (entry,) = store.audit_log(MODEL_A)
    assert (entry.action, entry.outcome, entry.details) == ("upload", "accepted", {"job": "job-1"})
    with pytest.raises(JobExists):
        store.create_job(job, audit=[_audit("upload", "accepted", details={"job": "job-1"})])
    assert len(store.audit_log(MODEL_A)) == 1  # the job refused, its entry was not written


def test_audit_log_pages_newest_first_per_model(store: CalibrationStore) -> None:
    for i in range(7):
        store.append_audit(_audit(f"action-{i}", details={"i": i, "nested": {"ok": True}}))
    store.append_audit(NewAuditEntry(model_hash=MODEL_B, who="bob", action="other", outcome="done"))
    first = store.audit_log(MODEL_A, limit=3)
    assert [e.action for e in first] == ["action-6", "action-5", "action-4"]
    second = store.audit_log(MODEL_A, before=first[-1].seq, limit=3)
    assert [e.action for e in second] == ["action-3", "action-2", "action-1"]
    last = store.audit_log(MODEL_A, before=second[-1].seq, limit=3)
    assert [(e.action, dict(e.details)) for e in last] == [("action-0", {"i": 0, "nested": {"ok": True}})]


def test_the_database_refuses_to_edit_the_audit_trail(store: CalibrationStore, store_url: str) -> None:
    store.append_audit(_audit())
    for sql in ("UPDATE calib_audit SET who = 'mallory'", "DELETE FROM calib_audit"):
        with pytest.raises(Exception, match="immutable"):
            rawdb.query(store_url, sql)
    assert store.audit_log(MODEL_A)[0].who == "alice"
