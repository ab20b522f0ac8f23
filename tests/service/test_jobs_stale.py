"""A job whose server process died is reported failed by the others, naming the dead process."""

from __future__ import annotations

import os
import signal
import socket
from datetime import UTC, datetime, timedelta
from pathlib import Path, PurePosixPath

from calibration_store import JobRecord, open_store
from service.calibration.jobs import STALE_AFTER
from tests.service.live import ADMIN_TOKEN, LiveServer, batch_zip, count_instances

COPIES = 6  # the samples, 6 times over: seconds of scoring, so the kill lands mid-job


def repeated(copies: int):
    """A batch mutation: every image (and its annotations) `copies` times, under new names."""

    def mutate(doc: dict, files: dict[str, bytes]) -> None:
        images, annotations = list(doc["images"]), list(doc["annotations"])
        next_image = max(image["id"] for image in images) + 1
        next_annotation = max(a["id"] for a in annotations) + 1
        for copy in range(1, copies):
            for image in images:
                path = PurePosixPath(image["file_name"])
                name = str(path.with_name(f"copy{copy}-{path.name}"))
                files[name] = files[image["file_name"]]
                doc["images"].append({**image, "id": next_image, "file_name": name})
                for annotation in (a for a in annotations if a["image_id"] == image["id"]):
                    doc["annotations"].append({**annotation, "id": next_annotation, "image_id": next_image})
                    next_annotation += 1
                next_image += 1

    return mutate




def test_a_killed_servers_job_is_reported_failed(tmp_path: Path, samples_dir: Path, coco: dict) -> None:
    store_url = f"sqlite://{tmp_path}/shared/calibration.db"
    with (
        LiveServer(tmp_path / "a", admin_token=ADMIN_TOKEN, store_url=store_url) as a,
        LiveServer(tmp_path / "b", admin_token=ADMIN_TOKEN, store_url=store_url) as b,
    ):
        response = a.upload(batch_zip(samples_dir, coco, mutate=repeated(COPIES)), activate=True)
        assert response.status_code == 202, response.text
        os.kill(a.process.pid, signal.SIGKILL)
        assert a.process.wait(timeout=10) == -signal.SIGKILL
        job_id, owner = response.json()["id"], f"{socket.gethostname()}:{a.process.pid}"

        with open_store(store_url) as store:
            row = store.get_job(job_id)
            assert row is not None and row.owner == owner
            assert row.state in ("queued", "running"), f"the kill must land mid-job: {row}"
            assert row.total == COPIES * count_instances(coco)
            # its heartbeat is recent: B still reports what the row says
            assert b.job(job_id)["state"] == row.state
            # the silence outlasts the limit (written as the dead process left it, only older)
            store.update_job(job_id, heartbeat_at=datetime.now(UTC) - STALE_AFTER - timedelta(seconds=5))

        job = b.job(job_id)
        assert job["state"] == "failed", job
        assert job["finished_at"] is not None and job["result"] == {}
        (error,) = job["errors"]
        assert owner in error and "stopped" in error and "nothing was stored" in error, error
        assert "/v1/admin/calibrations" in error, error
        assert b.versions() == [1], "the killed job stored no version"
        assert b.client.get("/readyz").json()["active_calibration"] == 1


def test_a_silent_job_row_is_reported_failed(tmp_path: Path) -> None:
    """Rows written through the store API: stale unfinished ones fail, fresh or finished ones stay."""
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
                    JobRecord(id=job_id, kind="calibration", owner="node-7:31337", created_at=old,
                              heartbeat_at=heartbeat_at, state=state, done=3, total=9)
                )  # fmt: skip
        for job_id in ("stale", "stale-queued"):
            job = server.job(job_id)
            assert (job["state"], job["done"], job["total"]) == ("failed", 3, 9), job
            assert "node-7:31337" in job["errors"][0] and "nothing was stored" in job["errors"][0], job
        assert server.job("fresh")["state"] == "running"
        assert server.job("finished")["state"] == "succeeded"
