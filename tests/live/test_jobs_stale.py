"""A job whose server process died is reported interrupted by the others, nothing of it is
stored, and it is never left running: a server that can read its kept upload (sharing the data
directory, or the same server restarted) takes it over; once nobody did, any server stores it
interrupted, saying why.

A real SIGKILL of a real server at the worst moments, held there by a lock this test takes:
with the version written but not committed (PostgreSQL: its audit entries wait; SQLite: its write
waits on the WAL write lock), and right after the commit (PostgreSQL: its next read waits).
Either the version is active and its job succeeded, or nothing was written and the job is
interrupted and retryable.
"""

from __future__ import annotations

import os
import signal
import socket
import time
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime, timedelta
from pathlib import Path

import psycopg
import pytest

from benchmarks.faults_clients import long_batch
from benchmarks.faults_store import WalLocks
from calibration_store import JobRecord, open_store
from service.infra.job_engine import STALE_AFTER, SWEEP_S, TAKEOVER_GRACE
from tests.live.server import LiveServer
from tests.samples import batch_zip, count_instances
from tests.service_calls import ADMIN_TOKEN, wait_until

COPIES = 6  # the samples, 6 times over: seconds of scoring, so the kill lands mid-job


def age_heartbeat(store_url: str, job_id: str, silence: timedelta = STALE_AFTER) -> None:
    """Make the dead process's silence outlast ``silence`` (the row as it left it, only older)."""
    with open_store(store_url) as store:
        store.update_job(job_id, heartbeat_at=datetime.now(UTC) - silence - timedelta(seconds=5))


def taken_over(server: LiveServer, job_id: str) -> str:
    """Wait for a server's sweep to take the stale job over; the id of the job that retries it."""
    deadline = time.monotonic() + SWEEP_S + 30
    while "retried_as" not in (old := server.job(job_id))["result"]:
        assert time.monotonic() < deadline, f"job {job_id} not taken over: {old}"
        time.sleep(0.2)
    assert old["state"] == "interrupted", old
    return old["result"]["retried_as"]


def killed(server: LiveServer) -> None:
    assert server.process.wait(timeout=60) == -signal.SIGKILL, server.log()


def test_a_killed_servers_job_is_interrupted_and_taken_over_by_its_restart(
    tmp_path: Path, samples_dir: Path, coco: dict
) -> None:
    store_url = f"sqlite://{tmp_path}/shared/calibration.db"
    body = long_batch(COPIES)
    with (
        LiveServer(tmp_path / "a", admin_token=ADMIN_TOKEN, store_url=store_url) as a,
        LiveServer(tmp_path / "b", admin_token=ADMIN_TOKEN, store_url=store_url) as b,
    ):
        response = a.upload(body, activate=True, force=True, reason="six copies")
        assert response.status_code == 202, response.text
        os.kill(a.process.pid, signal.SIGKILL)
        killed(a)
        job_id, owner = response.json()["id"], f"{socket.gethostname()}:{a.process.pid}"
        with open_store(store_url) as store:
            row = store.get_job(job_id)
            assert row is not None and row.owner == owner
            assert row.state in ("queued", "running"), f"the kill must land mid-job: {row}"
            assert row.total == COPIES * count_instances(coco)
        assert b.job(job_id)["state"] == row.state  # its heartbeat is recent: B reports the row
        age_heartbeat(store_url, job_id)

        job = b.job(job_id)
        assert job["state"] == "interrupted", job
        assert job["finished_at"] is not None and job["result"] == {} and job["version"] is None
        (error,) = job["errors"]
        assert owner in error and "stopped" in error and "Nothing was stored" in error, error
        assert f"/v1/admin/jobs/{job_id}/retry" in error, error
        assert b.versions() == [1], "the killed job stored no version"
        # B has its own data directory: the upload is kept in A's
        refused = b.client.post(f"/v1/admin/jobs/{job_id}/retry", headers=b.admin)
        assert refused.status_code == 409 and "not kept in this server's data directory" in refused.text

        with LiveServer(tmp_path / "a", admin_token=ADMIN_TOKEN, store_url=store_url) as again:
            new = again.wait_job(taken_over(again, job_id))
            assert new["state"] == "succeeded" and new["result"]["activated"], new
            assert again.versions() == [1, 2] and new["version"] == 2
            entries = again.client.get("/v1/admin/audit", headers=again.admin).json()["entries"]
            retry = next(e for e in entries if e["action"] == "retry")
            assert (retry["who"], retry["details"]) == ("takeover", {"job": job_id, "new_job": new["id"]})
            assert retry["client"] == f"{socket.gethostname()}:{again.process.pid}"
            again_refused = again.client.post(f"/v1/admin/jobs/{job_id}/retry", headers=again.admin)
            assert again_refused.status_code == 409, again_refused.text
            assert not (tmp_path / "a" / "jobs" / new["id"]).exists(), "a finished job's upload was kept"


#: a server waiting on a test's lock waits this long (the store timeout) rather than failing
HELD_STORE_TIMEOUT_S = 60
#: the version and its activation written, its audit entries waiting on the lock: not committed
WRITTEN = (
    "SELECT count(*) FROM pg_stat_activity a WHERE a.wait_event_type = 'Lock'"
    " AND a.query LIKE 'INSERT INTO calib_audit%' AND EXISTS (SELECT 1 FROM pg_locks l"
    " WHERE l.pid = a.pid AND l.granted AND l.relation = 'calib_versions'::regclass"
    " AND l.mode = 'RowExclusiveLock')"
)
#: committed, the job's next read of its new version waiting on the lock
COMMITTED = (
    "SELECT count(*) FROM pg_stat_activity WHERE wait_event_type = 'Lock'"
    " AND query LIKE 'SELECT % FROM calib_versions WHERE model_hash = % AND number = %'"
)


def observed(watcher: psycopg.Connection, query: str, what: str, *params: object) -> None:
    deadline = time.monotonic() + HELD_STORE_TIMEOUT_S
    while watcher.execute(query, params or None).fetchone() == (0,):
        assert time.monotonic() < deadline, f"the job never reached {what}"
        time.sleep(0.01)


def sigkill_on_postgres(server: LiveServer, store_url: str, moment: str) -> str:
    """Upload, and SIGKILL the server while its job waits on a lock this test holds: on its audit
    entries (the version written, not committed), or on the read right after the commit."""
    with (
        psycopg.connect(store_url, autocommit=True) as watcher,
        psycopg.connect(store_url) as audit_lock,
        psycopg.connect(store_url) as versions_lock,
        ThreadPoolExecutor(1) as locker,
    ):
        response = server.upload(long_batch(2), activate=True, force=True, reason="crash test")
        assert response.status_code == 202, response.text
        audit_lock.execute("LOCK TABLE calib_audit IN EXCLUSIVE MODE")  # the job's inserts wait
        observed(watcher, WRITTEN, "its audit entries")
        if moment == "version-committed":  # granted once the job commits; its next read waits
            locker_pid = versions_lock.info.backend_pid
            taken = locker.submit(versions_lock.execute, "LOCK TABLE calib_versions IN ACCESS EXCLUSIVE MODE")
            queued = "SELECT count(*) FROM pg_locks WHERE pid = %s AND NOT granted"
            observed(watcher, queued, "the versions lock queued", locker_pid)
            audit_lock.rollback()
            taken.result(timeout=HELD_STORE_TIMEOUT_S)
            observed(watcher, COMMITTED, "the read after its commit")
        os.kill(server.process.pid, signal.SIGKILL)
        killed(server)
        versions_lock.rollback()
        audit_lock.rollback()
    return response.json()["id"]


def sigkill_on_sqlite(server: LiveServer, store_url: str) -> str:
    """Upload, take the WAL write lock, and SIGKILL the server once its job scored every instance
    and waits on the lock to write the version (an uncommitted SQLite transaction leaves the same
    file as one never begun: its WAL frames have no commit)."""
    locks = WalLocks(Path(store_url.removeprefix("sqlite://")), WalLocks.WRITE_LOCK)
    response = server.upload(long_batch(2), activate=True, force=True, reason="crash test")
    assert response.status_code == 202, response.text
    job_id = response.json()["id"]
    locks.take()
    try:
        wait_until(
            lambda: (job := server.job(job_id))["done"] == job["total"],
            "every instance scored",
            HELD_STORE_TIMEOUT_S,
        )
        time.sleep(1.0)  # its reads of the active version, then the write that waits
        os.kill(server.process.pid, signal.SIGKILL)
        killed(server)
    finally:
        locks.release()
    return job_id


@pytest.mark.parametrize("moment", ["version-written", "version-committed"])
def test_sigkill_at_the_worst_moment_leaves_all_or_nothing(
    postgres_url: str, moment: str, tmp_path: Path
) -> None:
    data = tmp_path / "data"
    settings = {"admin_token": ADMIN_TOKEN, "store_url": postgres_url}
    server = LiveServer(data, {"STORE_TIMEOUT_SECONDS": HELD_STORE_TIMEOUT_S}, **settings).start()
    try:
        job_id = sigkill_on_postgres(server, postgres_url, moment)
    finally:
        server.stop()
    after_the_kill(data, settings, job_id, moment)


def test_sigkill_while_the_version_is_written_on_sqlite_leaves_nothing(tmp_path: Path) -> None:
    data = tmp_path / "data"
    settings = {"admin_token": ADMIN_TOKEN, "store_url": f"sqlite://{tmp_path}/shared/calibration.db"}
    server = LiveServer(data, {"STORE_TIMEOUT_SECONDS": HELD_STORE_TIMEOUT_S}, **settings).start()
    try:
        job_id = sigkill_on_sqlite(server, settings["store_url"])
    finally:
        server.stop()
    after_the_kill(data, settings, job_id, "version-written")


def after_the_kill(data: Path, settings: dict[str, str], job_id: str, moment: str) -> None:
    """All of the job or none of it, seen by the server restarted on the same data."""
    assert (data / "jobs" / job_id).is_dir(), "the upload of an unfinished job must be kept"
    if moment == "version-written":
        age_heartbeat(settings["store_url"], job_id)

    with LiveServer(data, **settings) as restarted:
        active = restarted.client.get("/readyz").json()["active_calibration"]
        job = restarted.job(job_id)
        if moment == "version-committed":  # all of it: version, activation, the job's success
            assert (job["state"], job["version"], active) == ("succeeded", 2, 2), job
            assert restarted.versions() == [1, 2]
            wait_until(lambda: not (data / "jobs" / job_id).exists(), "the spent upload is removed")
            return
        assert (job["state"], job["version"]) == ("interrupted", None), job  # none of it
        assert active == 1 or job["result"].get("retried_as"), "only its takeover may activate"
        new = restarted.wait_job(taken_over(restarted, job_id))
        assert (new["state"], new["version"]) == ("succeeded", 2), new
        assert restarted.client.get("/readyz").json()["active_calibration"] == 2
        entries = restarted.client.get("/v1/admin/audit", headers=restarted.admin).json()["entries"]
        assert {(e["action"], e["outcome"]) for e in entries[:3]} == {
            ("retry", "accepted"),
            ("activation", "forced"),
            ("calibration", "stored"),
        }  # the retry's entry and the job's race


def test_a_silent_job_row_is_reported_interrupted(tmp_path: Path) -> None:
    """Rows written through the store API: stale unfinished ones are interrupted, others stay."""
    store_url = f"sqlite://{tmp_path}/shared/calibration.db"
    now = datetime.now(UTC)
    old = now - STALE_AFTER - timedelta(seconds=1)
    with LiveServer(tmp_path / "a", admin_token=ADMIN_TOKEN, store_url=store_url) as server:
        with open_store(store_url) as store:
            for job_id, heartbeat_at, state in (
                ("stale", old, "running"),
                ("stale-queued", old, "queued"),
                ("fresh", now, "running"),
                ("finished", old, "succeeded"),
            ):
                store.create_job(
                    JobRecord(
                        id=job_id,
                        kind="calibration",
                        owner="node-7:31337",
                        created_at=old,
                        heartbeat_at=heartbeat_at,
                        state=state,
                        done=3,
                        total=9,
                    )
                )
        for job_id in ("stale", "stale-queued"):
            job = server.job(job_id)
            assert (job["state"], job["done"], job["total"]) == ("interrupted", 3, 9), job
            assert "node-7:31337" in job["errors"][0] and "Nothing was stored" in job["errors"][0], job
        assert server.job("fresh")["state"] == "running"
        assert server.job("finished")["state"] == "succeeded"


def test_a_job_queued_at_shutdown_is_interrupted_and_retried(
    tmp_path: Path, samples_dir: Path, coco: dict
) -> None:
    """A job still queued when the server stops is stored interrupted (a final state): the
    retry claims its kept upload by moving it, once."""
    data = tmp_path / "data"
    server = LiveServer(data, admin_token=ADMIN_TOKEN, calibration_workers=1).start()
    try:
        first = server.upload(long_batch(COPIES))
        second = server.upload(batch_zip(samples_dir, coco, images=3))
        assert first.status_code == second.status_code == 202, (first.text, second.text)
        queued = second.json()["id"]
        assert server.job(queued)["state"] == "queued"
    finally:
        server.stop()
    with LiveServer(data, admin_token=ADMIN_TOKEN) as restarted:
        job = restarted.job(queued)
        assert job["state"] == "interrupted" and "stopped before the job started" in job["errors"][0], job
        retried = restarted.client.post(f"/v1/admin/jobs/{queued}/retry", headers=restarted.admin)
        assert retried.status_code == 202, retried.text
        new = restarted.wait_job(retried.json()["id"])
        assert new["state"] == "succeeded" and new["result"]["added"] == count_instances(coco, images=3), new
        again = restarted.client.post(f"/v1/admin/jobs/{queued}/retry", headers=restarted.admin)
        assert again.status_code == 409, again.text


def test_a_killed_replicas_job_is_taken_over_by_a_replica_sharing_its_data_directory(
    postgres_url: str, tmp_path: Path, coco: dict
) -> None:
    """Two replicas on one PostgreSQL store and one data directory (a shared volume): the job of
    the one SIGKILLed is run again by the other, once; one version."""
    data = tmp_path / "shared-data"
    settings = {"admin_token": ADMIN_TOKEN, "store_url": postgres_url}
    with LiveServer(data, **settings) as a, LiveServer(data, **settings) as b:
        response = a.upload(long_batch(COPIES), note="killed on A")
        assert response.status_code == 202, response.text
        job_id = response.json()["id"]
        os.kill(a.process.pid, signal.SIGKILL)
        killed(a)
        assert b.job(job_id)["state"] in ("queued", "running"), "the kill must land mid-job"
        age_heartbeat(postgres_url, job_id)

        new = b.wait_job(taken_over(b, job_id))
        assert (new["state"], new["version"], new["total"]) == (
            "succeeded",
            2,
            COPIES * count_instances(coco),
        )
        assert b.versions() == [1, 2]
        with open_store(postgres_url) as store:
            assert store.get_job(new["id"]).owner == f"{socket.gethostname()}:{b.process.pid}"
            assert store.stale_jobs(datetime.now(UTC)) == [], "no job is left unfinished"
        refused = b.client.post(f"/v1/admin/jobs/{job_id}/retry", headers=b.admin)
        assert refused.status_code == 409 and f"retried already, as job {new['id']}" in refused.text


def test_a_killed_replicas_job_nobody_can_read_is_stored_interrupted(
    postgres_url: str, tmp_path: Path
) -> None:
    """Two replicas on one PostgreSQL store, each with its own data directory: the job of the one
    SIGKILLed cannot be run elsewhere; once the grace for a takeover has passed, the other stores
    it interrupted, saying why, and never leaves it running."""
    settings = {"admin_token": ADMIN_TOKEN, "store_url": postgres_url}
    with LiveServer(tmp_path / "a", **settings) as a, LiveServer(tmp_path / "b", **settings) as b:
        response = a.upload(long_batch(COPIES))
        assert response.status_code == 202, response.text
        job_id, owner = response.json()["id"], f"{socket.gethostname()}:{a.process.pid}"
        os.kill(a.process.pid, signal.SIGKILL)
        killed(a)
        age_heartbeat(postgres_url, job_id)  # stale, within the grace: B cannot take it, waits
        time.sleep(SWEEP_S + 1)
        with open_store(postgres_url) as store:
            assert store.get_job(job_id).state in ("queued", "running"), "stored before the grace ended"
        age_heartbeat(postgres_url, job_id, STALE_AFTER + TAKEOVER_GRACE)

        with open_store(postgres_url) as store:
            wait_until(
                lambda: store.get_job(job_id).state == "interrupted",
                "the job stored interrupted",
                timeout=SWEEP_S + 30,
            )
            row = store.get_job(job_id)
        assert row.finished_at is not None and row.version is None
        assert owner in row.errors[0] and "Nothing was stored" in row.errors[0], row.errors
        assert "its upload is not readable here" in row.errors[-1], row.errors
        assert row.errors[-1].endswith("upload the batch again."), row.errors
        assert b.job(job_id)["errors"] == list(row.errors), "every replica reports the stored row"
        assert b.versions() == [1]
