"""A job accepted by one server process is polled to success on another sharing the store.

PostgreSQL stands for replicas behind a load balancer; one SQLite file stands for the
worker processes of one host (CKS_WORKERS=2).
"""

from __future__ import annotations

import socket
from pathlib import Path

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
