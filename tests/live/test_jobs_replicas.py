"""A job accepted by one server process is polled to success on another sharing the store.

PostgreSQL stands for replicas behind a load balancer; one SQLite file stands for the
worker processes of one host (CKS_WORKERS=2).
"""

from __future__ import annotations

import socket
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest

from calibration_store import open_store
from tests.live.server import LiveServer
from tests.samples import batch_zip, count_instances
from tests.service_calls import ADMIN_TOKEN, assert_problem

IMAGES = 4


@pytest.fixture(params=["postgres", "sqlite"])
def shared_store_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    if request.param == "postgres":
        return request.getfixturevalue("postgres_url")
    return f"sqlite://{tmp_path}/shared/calibration.db"


def test_upload_on_a_poll_on_b(shared_store_url: str, tmp_path: Path, samples_dir: Path, coco: dict) -> None:
    total = count_instances(coco, images=IMAGES)
    # Sequential start: the first server stores the bundled calibration, the second finds it.
    with (
        LiveServer(tmp_path / "a", admin_token=ADMIN_TOKEN, store_url=shared_store_url) as a,
        LiveServer(tmp_path / "b", admin_token=ADMIN_TOKEN, store_url=shared_store_url) as b,
    ):
        assert a.versions() == b.versions() == [1]
        response = a.upload(batch_zip(samples_dir, coco, images=IMAGES), note="from A")
        assert response.status_code == 202, response.text
        accepted = response.json()
        job_id = accepted["id"]

        # the row exists before the 202, so B knows the job from the first poll on
        first = b.job(job_id)
        assert first["state"] in ("queued", "running", "succeeded"), first
        assert (first["id"], first["kind"], first["total"]) == (job_id, "calibration", total)
        assert first["created_at"] == accepted["created_at"]

        job = b.wait_job(job_id)
        assert job["state"] == "succeeded", job
        assert job["done"] == job["total"] == total and job["errors"] == []
        assert job["finished_at"] is not None
        version = job["result"]["version"]
        assert (job["result"]["instances"], job["result"]["activated"]) == (total, False)
        assert job["version"] == version
        assert version == 2
        assert a.job(job_id) == job, "both servers report the same stored job"

        assert a.versions() == b.versions() == [1, 2]
        with open_store(shared_store_url) as store:
            row = store.get_job(job_id)
        assert row.owner == f"{socket.gethostname()}:{a.process.pid}", "A ran the job; B only reported it"

        body = assert_problem(b.client.get("/v1/admin/jobs/nope", headers=b.admin), 404, "nope")
        assert "replica" not in body["detail"], body


def test_identical_uploads_at_once_on_two_replicas_store_one_version(
    postgres_url: str, tmp_path: Path, samples_dir: Path, coco: dict
) -> None:
    """Two replicas on one PostgreSQL store, two calibration workers each, the same batch sent to
    both twice at the same moment: one version. The others are refused with the duplicate's words,
    at the upload (409) when the version was stored by then, else in their job, which the store
    refuses (a rule of the store, not a check of one process), with duplicate_of in the trail."""
    body = batch_zip(samples_dir, coco, images=IMAGES)
    settings = {"admin_token": ADMIN_TOKEN, "store_url": postgres_url, "calibration_workers": 2}
    with LiveServer(tmp_path / "a", **settings) as a, LiveServer(tmp_path / "b", **settings) as b:
        targets = [a, b, a, b]
        start = threading.Barrier(len(targets))

        def send(server: LiveServer) -> httpx.Response:
            with httpx.Client(base_url=server.url, headers=server.admin, timeout=60) as client:
                start.wait()
                return client.post(
                    "/v1/admin/calibrations", content=body, headers={"Content-Type": "application/zip"}
                )

        with ThreadPoolExecutor(len(targets)) as pool:
            answers = list(pool.map(send, targets))
        jobs = [a.wait_job(r.json()["id"]) for r in answers if r.status_code == 202]
        stored = [job for job in jobs if job["state"] == "succeeded"]
        assert len(stored) == 1, jobs
        version = stored[0]["version"]
        assert a.versions() == b.versions() == [1, version] == [1, 2]

        refused_jobs = [job for job in jobs if job is not stored[0]]
        for job in refused_jobs:
            assert job["state"] == "failed", job
            assert f"would make a version equal to calibration version {version}" in job["errors"][0], job
        for refused in (r for r in answers if r.status_code != 202):
            assert_problem(refused, 409, f"equal to calibration version {version}")
        failed = [
            e
            for e in b.client.get("/v1/admin/audit", headers=b.admin).json()["entries"]
            if (e["action"], e["outcome"]) == ("calibration", "failed")
        ]
        assert sorted(e["details"]["job"] for e in failed) == sorted(j["id"] for j in refused_jobs)
        assert all(e["details"]["duplicate_of"] == version for e in failed), failed
        print(f"answers {[r.status_code for r in answers]}, jobs {[j['state'] for j in jobs]}")
