"""JobRunner writes its jobs through to a real SQLite store and survives store trouble."""

from __future__ import annotations

import sqlite3
import threading
import time
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest

from calibration_store import JobRecord
from calibration_store.sqlite import SQLiteStore
from service.errors import InvalidInput
from service.infra import job_engine as jobs
from service.infra.job_engine import JobProgress, JobRunner, reported
from tests.service_calls import wait_until

OWNER = "test-host:4242"


class CountingStore(SQLiteStore):
    """A real SQLite store that also remembers every update_job call."""

    def __init__(self, path: Path, **options: Any) -> None:
        super().__init__(path, **options)
        self.updates: list[dict[str, Any]] = []

    def update_job(self, job_id: str, **fields: Any) -> JobRecord:
        self.updates.append(fields)
        return super().update_job(job_id, **fields)


@pytest.fixture
def store(tmp_path: Path) -> Iterator[CountingStore]:
    opened = CountingStore(tmp_path / "calibration.db", busy_timeout_s=0.2)
    yield opened
    opened.close()


@pytest.fixture
def runner(store: CountingStore) -> Iterator[JobRunner]:
    started = JobRunner(store, workers=1, owner=OWNER)
    yield started
    started.shutdown()


def state_of(store: CountingStore, job_id: str) -> str | None:
    job = store.get_job(job_id)
    return None if job is None else job.state


def test_job_lifecycle_is_written_through(store: CountingStore, runner: JobRunner) -> None:
    go = threading.Event()

    def work(progress: JobProgress) -> dict:
        assert go.wait(10)
        progress.advance(3)
        return {"version": 4}

    job = runner.submit("calibration", work, total=3)
    stored = store.get_job(job.id)
    assert stored is not None, "the row must exist when submit returns (before the 202)"
    assert (stored.kind, stored.owner, stored.total, stored.state in ("queued", "running")) == (
        "calibration",
        OWNER,
        3,
        True,
    )
    wait_until(lambda: state_of(store, job.id) == "running", what="running written")
    go.set()
    wait_until(lambda: state_of(store, job.id) == "succeeded", what="success written")
    final = store.get_job(job.id)
    assert (final.done, final.total, final.result, final.errors) == (3, 3, {"version": 4}, ())
    assert final.finished_at is not None and final.heartbeat_at >= final.finished_at
    assert runner.get(job.id) == final


def test_failed_job_keeps_its_errors(store: CountingStore, runner: JobRunner) -> None:
    def work(progress: JobProgress) -> dict:
        raise InvalidInput("image 7 ('a.png'): cannot decode", errors=["truncated"])

    job = runner.submit("calibration", work, total=1)
    wait_until(lambda: state_of(store, job.id) == "failed", what="failure written")
    final = store.get_job(job.id)
    assert final.errors == ("image 7 ('a.png'): cannot decode", "truncated")
    assert final.result == {} and final.finished_at is not None


def test_progress_is_written_about_once_a_second(store: CountingStore, runner: JobRunner) -> None:
    seen_mid_run: list[int] = []

    def work(progress: JobProgress) -> dict:
        for i in range(250):  # 2.5 s of progress, 100 steps a second
            progress.advance()
            time.sleep(0.01)
            if i == 200:
                seen_mid_run.append(store.get_job(job_id).done)
        return {}

    job_id = ""
    job = runner.submit("calibration", work, total=250)
    job_id = job.id
    wait_until(lambda: state_of(store, job.id) == "succeeded", what="success written")
    assert store.get_job(job.id).done == 250
    assert seen_mid_run and 0 < seen_mid_run[0] <= 201, "progress must reach the store while running"
    writes = len(store.updates)
    # running + about one progress write a second for ~2.5 s + the final state
    assert 3 <= writes <= 6, f"{writes} writes for 250 progress steps: {store.updates}"


def test_heartbeat_without_progress(
    store: CountingStore, runner: JobRunner, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(jobs, "HEARTBEAT_S", 0.5)
    go = threading.Event()
    job = runner.submit("calibration", lambda progress: {} if go.wait(10) else {"late": True})
    wait_until(lambda: state_of(store, job.id) == "running", what="running written")
    first = store.get_job(job.id).heartbeat_at
    wait_until(lambda: store.get_job(job.id).heartbeat_at > first, what="a fresh heartbeat")
    assert store.get_job(job.id).done == 0
    go.set()
    wait_until(lambda: state_of(store, job.id) == "succeeded", what="success written")


def _hold_write_lock(path: Path) -> sqlite3.Connection:
    blocker = sqlite3.connect(path, isolation_level=None)
    blocker.execute("BEGIN IMMEDIATE")
    return blocker


def test_store_trouble_does_not_kill_the_job(store: CountingStore, runner: JobRunner) -> None:
    blocked, go = threading.Event(), threading.Event()

    def work(progress: JobProgress) -> dict:
        assert blocked.wait(10)
        for _ in range(20):  # progress while every write fails (the store is locked)
            progress.advance()
            time.sleep(0.05)
        go.set()
        return {"version": 9}

    job = runner.submit("calibration", work, total=20)
    wait_until(lambda: state_of(store, job.id) == "running", what="running written")
    blocker = _hold_write_lock(store.path)
    try:
        blocked.set()
        assert go.wait(10)
        time.sleep(0.5)  # the first attempts at the final write fail too
        assert store.get_job(job.id).state == "running"
    finally:
        blocker.execute("ROLLBACK")
        blocker.close()
    wait_until(lambda: state_of(store, job.id) == "succeeded", what="success written after the outage")
    final = store.get_job(job.id)
    assert (final.done, final.result) == (20, {"version": 9})


def test_final_state_lands_after_the_retries_run_out(
    store: CountingStore, runner: JobRunner, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(jobs, "FINAL_WRITE_ATTEMPTS", 1)
    go, finished = threading.Event(), threading.Event()

    def work(progress: JobProgress) -> dict:
        assert go.wait(10)
        finished.set()
        return {"version": 1}

    job = runner.submit("calibration", work)
    wait_until(lambda: state_of(store, job.id) == "running", what="running written")
    blocker = _hold_write_lock(store.path)
    try:
        go.set()
        assert finished.wait(10)
        time.sleep(1.0)  # the one final attempt failed; the writer thread keeps trying
        assert store.get_job(job.id).state == "running"
    finally:
        blocker.execute("ROLLBACK")
        blocker.close()
    wait_until(lambda: state_of(store, job.id) == "succeeded", what="success written later")


def test_a_silent_unfinished_job_is_reported_interrupted(store: CountingStore, runner: JobRunner) -> None:
    now = datetime.now(UTC)
    old = now - timedelta(seconds=75)

    def row(job_id: str, owner: str, heartbeat_at: datetime, state: str, **fields: Any) -> None:
        store.create_job(
            JobRecord(
                id=job_id,
                kind="calibration",
                owner=owner,
                created_at=old,
                heartbeat_at=heartbeat_at,
                state=state,
                **fields,
            )
        )

    row("dead-running", "gone-host:999", old, "running", done=2, total=10)
    row("dead-queued", "gone-host:999", old, "queued", done=2, total=10)
    row("alive", "other:1", now - timedelta(seconds=30), "running")
    row("done-long-ago", "gone-host:999", old, "succeeded", finished_at=old)
    for job_id in ("dead-running", "dead-queued"):
        job = runner.get(job_id)
        assert job.state == "interrupted" and job.finished_at == old and job.done == 2
        (error,) = job.errors
        assert "gone-host:999" in error and "stopped" in error and "Nothing was stored" in error, error
        assert f"/v1/admin/jobs/{job_id}/retry" in error, error
        assert store.get_job(job_id).state != "interrupted", "reporting must not rewrite the row"
    assert runner.get("alive").state == "running"
    assert runner.get("done-long-ago").state == "succeeded"
    assert runner.get("unknown") is None


def stale_row(store: CountingStore, job_id: str, kind: str, silent: timedelta) -> None:
    heartbeat_at = datetime.now(UTC) - silent
    store.create_job(
        JobRecord(
            id=job_id, kind=kind, owner="gone-host:999", created_at=heartbeat_at, heartbeat_at=heartbeat_at
        )
    )


def test_a_stale_job_is_offered_to_its_takeover_and_never_left_unfinished(store: CountingStore) -> None:
    """Every process looks after the stale jobs of the kinds it knows: one it can read is taken
    over; one nobody took over within the grace is stored interrupted, saying why; one of a kind
    nobody can take over is stored interrupted at once; an unknown kind is left alone."""
    just_stale = jobs.STALE_AFTER + timedelta(seconds=5)
    stale_row(store, "readable", "calibration", just_stale)
    stale_row(store, "elsewhere", "calibration", just_stale)
    stale_row(store, "given-up", "calibration", jobs.STALE_AFTER + jobs.TAKEOVER_GRACE + timedelta(seconds=5))
    stale_row(store, "audit", "audit", just_stale)
    stale_row(store, "other-kind", "export", just_stale)
    offered: list[str] = []

    def take_over(job: JobRecord) -> bool:
        offered.append(job.id)
        if job.id != "readable":
            return False
        store.update_job(
            job.id, state="interrupted", finished_at=datetime.now(UTC), result={"retried_as": "x"}
        )
        return True

    runner = JobRunner(store, workers=1, owner=OWNER)
    try:
        runner.on_stale("calibration", take_over)
        runner.on_stale("audit", None)
        wait_until(lambda: state_of(store, "audit") == "interrupted", "a stale audit is stored interrupted")
        wait_until(lambda: state_of(store, "given-up") == "interrupted", "a job nobody took over is stored")
    finally:
        runner.shutdown()
    assert sorted(set(offered)) == ["elsewhere", "given-up", "readable"]
    assert store.get_job("readable").result == {"retried_as": "x"}, "the takeover's own write stays"
    assert state_of(store, "elsewhere") == "queued", "within the grace a readable copy may still take it"
    assert state_of(store, "other-kind") == "queued"
    given_up = store.get_job("given-up")
    assert given_up.finished_at is not None and "gone-host:999" in given_up.errors[0]
    assert given_up.errors[-1].startswith("No server that can read its upload took it over"), given_up.errors
    assert "upload the batch again" in given_up.errors[-1]
    assert "not taken over by another process" in store.get_job("audit").errors[-1]


def test_staleness_limit() -> None:
    now = datetime.now(UTC)
    job = JobRecord(id="j", kind="k", owner="o", created_at=now, heartbeat_at=now, state="running")
    assert reported(job, now + jobs.STALE_AFTER) == job
    assert reported(job, now + jobs.STALE_AFTER + timedelta(seconds=1)).state == "interrupted"
    assert jobs.STALE_AFTER.total_seconds() >= 3 * jobs.HEARTBEAT_S, "a live job must never look stale"


def test_shutdown_interrupts_running_and_queued_jobs(store: CountingStore) -> None:
    """Not waited for: the running job is marked interrupted at once and stops at its next progress."""
    runner = JobRunner(store, workers=1, owner=OWNER)
    go, advanced = threading.Event(), []

    def scoring(progress: JobProgress) -> dict:
        go.wait(10)
        progress.advance()
        advanced.append(True)  # not reached: advance() raises once the service is stopping
        return {"first": True}

    first = runner.submit("calibration", scoring, total=2)
    second = runner.submit("calibration", lambda progress: {"second": True})
    wait_until(lambda: state_of(store, first.id) == "running", what="first running")
    assert state_of(store, second.id) == "queued"
    stopper = threading.Thread(target=runner.shutdown)
    stopper.start()
    wait_until(lambda: state_of(store, first.id) == "interrupted", what="the running job is interrupted")
    go.set()
    stopper.join(30)
    assert not stopper.is_alive() and not advanced
    running = store.get_job(first.id)
    assert "while the job was running (0/2 instances scored)" in running.errors[0], running.errors
    queued = store.get_job(second.id)
    assert queued.state == "interrupted" and "stopped before the job started" in queued.errors[0]
    assert f"/v1/admin/jobs/{second.id}/retry" in queued.errors[0]
