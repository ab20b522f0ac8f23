"""A full disk is a 507, never a 500: a real server on a real 40 MiB file system (tmpfs; the
tests run as root) that fills while it receives an upload, while it unzips it into its job's
folder, before the job's request is written (the store on PostgreSQL, held at that moment: see
``benchmarks.faults_disk.intake_held``), and while its job writes the version to the store
(SQLite, on the same disk).

Each time: what was written is removed at once, the refusal is in the audit trail, and the
service works again as soon as space is freed, without a restart.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from pathlib import Path

import pytest

from benchmarks.faults_clients import long_batch
from benchmarks.faults_disk import (
    audit_entries,
    fill,
    free_space,
    kept_files,
    many_small_files,
    serve_on,
    serve_on_held,
    small_disk,
    upload_refused_at_job_request,
)
from tests.live.server import LiveServer
from tests.service_calls import assert_problem, wait_until

COPIES = 6  # the samples, 6 times over (7.7 MB zipped): seconds of scoring


@pytest.fixture
def disk(tmp_path: Path) -> Iterator[Path]:
    with small_disk(tmp_path) as data:
        yield data


def latest_entry(server: LiveServer) -> dict:
    return audit_entries(server)[0]


def assert_refusal_audited(server: LiveServer, status: int) -> None:
    entry = latest_entry(server)
    assert (entry["action"], entry["outcome"]) == ("upload", "refused"), entry
    assert entry["details"]["status"] == status, entry


def assert_no_500(server: LiveServer) -> None:
    log = server.log()
    assert "status=500" not in log and "Traceback" not in log, log


def test_an_upload_received_on_a_full_disk_gets_507(disk: Path) -> None:
    body = long_batch(1)
    with serve_on(disk) as server:
        fill(disk, leave=len(body) // 2)  # the zip fills it halfway through
        response = server.upload(body)
        assert_problem(response, 507, "file system is full", "the upload could not be written", "retry")
        assert kept_files(server) == [], "the partial upload was left on the disk"
        assert_refusal_audited(server, 507)

        free_space(disk)
        assert server.calibrate(body)["result"]["version"] == 2  # no restart needed
        assert_no_500(server)


def test_an_upload_unzipped_into_its_job_on_a_full_disk_gets_507(disk: Path) -> None:
    """12,000 files of one byte pass the disk check (12 kB declared) but take 47 MiB of pages."""
    with serve_on(disk) as server:
        response = server.upload(many_small_files(12_000))
        assert_problem(response, 507, "file system is full", "the unzipped upload")
        assert kept_files(server) == [], "the unzipped files were left on the disk"
        assert not any((disk / "jobs").iterdir()), "the job's folder was left"
        assert_refusal_audited(server, 507)

        assert server.calibrate(long_batch(1))["result"]["version"] == 2  # the space is back at once
        assert_no_500(server)


def test_a_job_request_written_on_a_full_disk_gets_507(disk: Path, postgres_url: str) -> None:
    """The disk fills after the upload is unzipped into its job's folder, before the job's
    request.json is written: the intake reads the stored versions between the two, and the test
    holds that table locked (the store on PostgreSQL), fills the disk once the server waits on the
    lock, then lets it go."""
    body = long_batch(1)
    with serve_on_held(disk, postgres_url) as server:
        response = upload_refused_at_job_request(server, postgres_url, body).result()
        assert_problem(response, 507, "file system is full", "the upload's files")
        assert kept_files(server) == [], "the job's folder was left"
        assert_refusal_audited(server, 507)

        free_space(disk)
        assert server.calibrate(body)["result"]["version"] == 2
        assert_no_500(server)


def test_a_job_whose_version_finds_the_store_full_fails_and_is_retried(disk: Path) -> None:
    with serve_on(disk) as server:
        response = server.upload(long_batch(COPIES))
        assert response.status_code == 202, response.text
        job_id = response.json()["id"]
        fill(disk)  # while the job scores: its version, then its own state, find no room

        job = server.wait_job(job_id)
        assert job["state"] == "failed", job
        assert (
            job["errors"][0].startswith("disk full") and f"/v1/admin/jobs/{job_id}/retry" in job["errors"][0]
        )
        assert job["result"] == {"retryable": True}, job
        stored = sqlite3.connect(f"file:{disk / 'calibrations.db'}?mode=ro", uri=True)
        (row,) = stored.execute("SELECT state FROM calib_jobs WHERE id = ?", (job_id,)).fetchall()
        assert row[0] in ("queued", "running"), "the store took the failure: the disk was not full"
        assert server.job(job_id)["state"] == "failed", "a live process's job must not read interrupted"
        assert (disk / "jobs" / job_id).is_dir(), "a retryable job's upload must be kept"
        refused = server.client.post(
            "/v1/admin/calibrations/1/activate", json={"reason": "x"}, headers=server.admin
        )
        assert_problem(refused, 507, "disk is full")

        free_space(disk)
        wait_until(
            lambda: any(
                e["details"].get("status") == 507
                for e in audit_entries(server)
                if e["action"] == "activation"
            ),
            "the activation's refusal is in the audit trail once the store can take it",
        )
        wait_until(
            lambda: (
                stored.execute("SELECT state FROM calib_jobs WHERE id = ?", (job_id,)).fetchone()[0]
                == "failed"
            ),
            "the job's failure reaches the store once there is room",
        )
        stored.close()
        retried = server.client.post(f"/v1/admin/jobs/{job_id}/retry", headers=server.admin)
        assert retried.status_code == 202, retried.text
        new = server.wait_job(retried.json()["id"])
        assert (new["state"], new["version"]) == ("succeeded", 2), new
        # the job is reported succeeded before its runner removes the upload it no longer needs
        wait_until(lambda: kept_files(server) == [], "a finished job's upload is removed")
        assert_no_500(server)
