"""Replicas sharing a store: PostgreSQL stands for replicas behind a load balancer, one SQLite
file for the worker processes of one host.

- An activation on one is seen by the other at its next poll (the store is the one truth: two
  services in this process).
- A job accepted by one server process is polled to success on another; identical uploads at once
  on two replicas store one version.
- One monitoring truth for the fleet: shifted traffic (heavily occluded scenes) sent to replica A
  only, replica B raises the alarm, its answer covering both replicas; a camera spread over both
  counts each scene once; a restarted server continues its windows; a coverage audit run on one
  replica reaches the gauges of the other.

Jobs and drift windows belong to a process (host:pid): those tests run server processes.
"""

from __future__ import annotations

import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest

from calibration_store import open_store
from tests.api.in_process import InProcess
from tests.api.test_audits import run_audit
from tests.live.server import LiveServer
from tests.live.test_drift_streams import FRAMES_PER_SCENE, send, send_heavy_until_alarm
from tests.predict_client import instances_of, predict_ok
from tests.samples import Sample, batch_zip, count_instances, samples_by_image
from tests.service_calls import ADMIN_TOKEN, BUSY_MACHINE_MARGIN_S, ServiceCalls, assert_problem, wait_until
from tests.streams import render_scenes

POLL_S = 1.0  # the store's poll interval: a replica sees another's activation at its next poll
DEADLINE_S = 2 * POLL_S + BUSY_MACHINE_MARGIN_S
IMAGES = 4
SHARE_S = 0.5  # CKS_DRIFT_SHARE_SECONDS: short, to keep the test short
SCENES = 60


def wait_for_active(server: ServiceCalls, version: int, since: float) -> float:
    """Seconds from ``since`` until the server's /readyz reports ``version`` as active; fails
    beyond DEADLINE_S."""
    last = None
    while time.monotonic() - since < DEADLINE_S:
        response = server.client.get("/readyz")
        last = response.json() if response.status_code == 200 else response.text
        if response.status_code == 200 and last["active_calibration"] == version:
            return time.monotonic() - since
        time.sleep(0.1)
    raise AssertionError(f"replica did not report version {version} within {DEADLINE_S} s; last: {last}")


def test_replicas_share_the_active_version(
    postgres_url: str, tmp_path: Path, samples_dir: Path, coco: dict, samples: list[Sample]
) -> None:
    path, group = next(iter(samples_by_image(samples).items()))
    image, parameters = path.read_bytes(), {"instances": instances_of(group)}
    # Sequential start: the first replica stores the bundled calibration, the second finds it.
    with (
        InProcess(tmp_path / "a", admin_token=ADMIN_TOKEN, store_url=postgres_url) as a,
        InProcess(tmp_path / "b", admin_token=ADMIN_TOKEN, store_url=postgres_url) as b,
    ):
        assert a.versions() == b.versions() == [1]
        assert predict_ok(b.client, image, parameters)["calibration"]["version"] == 1

        job = a.calibrate(batch_zip(samples_dir, coco, images=4), activate=True, force=True, reason="small")
        activated_at = time.monotonic()
        version = job["result"]["version"]
        assert version == 2
        assert a.client.get("/readyz").json()["active_calibration"] == version

        wait_for_active(b, version, activated_at)  # within two polls, and a busy machine's margin
        assert predict_ok(b.client, image, parameters)["calibration"]["version"] == version
        assert b.versions() == [1, 2]

        # and the other way round: a rollback on B reaches A
        response = b.client.post(
            "/v1/admin/calibrations/1/activate", json={"reason": "rollback from B"}, headers=b.admin
        )
        assert response.status_code == 200, response.text
        wait_for_active(a, 1, time.monotonic())
        assert predict_ok(a.client, image, parameters)["calibration"]["version"] == 1
        log = a.client.get("/v1/admin/activations", headers=a.admin).json()["activations"]
        assert [(e["version"], e["reason"]) for e in log[-2:]] == [
            (2, "small"),
            (1, "rollback from B"),
        ]


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


def drift(url: str) -> dict:
    with httpx.Client(base_url=url, timeout=60) as client:  # a new connection: any worker answers
        response = client.get("/v1/admin/drift", headers={"Authorization": f"Bearer {ADMIN_TOKEN}"})
    assert response.status_code == 200, response.text
    return response.json()


def send_heavy_scenes(servers: list[ServiceCalls], scenes: int) -> None:
    """Each scene's frames sent to the servers in turn, as a round-robin proxy does."""
    turn = 0
    for (frame,) in render_scenes(range(9402, 9402 + scenes), 1, "heavy_occlusion"):
        for _ in range(FRAMES_PER_SCENE):
            send(servers[turn % len(servers)], frame)
            turn += 1


def test_shifted_traffic_to_one_replica_raises_the_alarm_read_from_another(
    postgres_url: str, tmp_path: Path
) -> None:
    settings = {"admin_token": ADMIN_TOKEN, "store_url": postgres_url, "drift_share_seconds": SHARE_S}
    with LiveServer(tmp_path / "a", **settings) as a, LiveServer(tmp_path / "b", **settings) as b:
        scenes, shifted = send_heavy_until_alarm(a)  # A alone: its own alarm, however many it takes
        assert shifted["alarm"], f"no alarm on A after {scenes} heavy scenes: {shifted['evidence']}"
        wait_until(lambda: drift(b.url)["alarm"], "replica B raises the alarm of A's traffic", timeout=30)
        frames = scenes * FRAMES_PER_SCENE
        wait_until(lambda: drift(b.url)["frames"] == frames, "B covers every frame A saw", timeout=30)
        time.sleep(3 * SHARE_S)  # A's last share written and read by B, B's by A
        seen_by_a, seen_by_b = drift(a.url), drift(b.url)
        assert seen_by_b["replicas"] == seen_by_a["replicas"] == 2, seen_by_b
        assert seen_by_b["frames"] == seen_by_a["frames"] == frames, seen_by_b
        assert seen_by_b["independent_looks"] == seen_by_a["independent_looks"], (seen_by_a, seen_by_b)
        assert seen_by_b["recorded"] == seen_by_a["recorded"] > 0
        assert 0 < seen_by_b["oldest_share_seconds"] < 5 * SHARE_S + 1, seen_by_b
        metrics = b.client.get("/metrics").text
        assert "cks_drift_alarm_any 1.0" in metrics and "cks_drift_replicas 2.0" in metrics

        a.stop()  # a stopped replica no longer counts once its row is stale
        wait_until(lambda: drift(b.url)["replicas"] == 1, "B covers itself alone", timeout=30)


def test_a_camera_spread_over_two_replicas_counts_each_scene_once(postgres_url: str, tmp_path: Path) -> None:
    """Each replica sees a first frame of every scene: alone, each would count it as a look."""
    settings = {"admin_token": ADMIN_TOKEN, "store_url": postgres_url, "drift_share_seconds": SHARE_S}
    with LiveServer(tmp_path / "a", **settings) as a, LiveServer(tmp_path / "b", **settings) as b:
        send_heavy_scenes([a, b], SCENES // 2)
        frames = SCENES // 2 * FRAMES_PER_SCENE
        wait_until(
            lambda: drift(b.url)["frames"] == drift(a.url)["frames"] == frames, "both see all", timeout=30
        )
        time.sleep(3 * SHARE_S)  # each replica's looks decided once the other's frames are shared
        seen_by_a, seen_by_b = drift(a.url), drift(b.url)
        assert seen_by_a["independent_looks"] == seen_by_b["independent_looks"], (seen_by_a, seen_by_b)
        # one process counts at most a look per scene (tests/live/test_drift_streams.py)
        assert 0.8 * (SCENES // 2) <= seen_by_a["independent_looks"] <= SCENES // 2, seen_by_a
        assert seen_by_a["evidence"] == seen_by_b["evidence"]


def test_a_restarted_server_continues_its_windows(tmp_path: Path) -> None:
    """SIGTERM writes the last share; the next process of this host takes it over."""
    settings = {"admin_token": ADMIN_TOKEN, "drift_share_seconds": SHARE_S}
    with LiveServer(tmp_path / "data", **settings) as before:
        send_heavy_scenes([before], 10)
        seen = drift(before.url)
    with LiveServer(tmp_path / "data", **settings) as after:
        wait_until(lambda: drift(after.url)["frames"] == seen["frames"], "the windows continue", timeout=30)
        continued = drift(after.url)
        assert continued["replicas"] == 1, continued
        assert continued["recorded"] >= seen["recorded"] > 0, (seen, continued)
        assert continued["independent_looks"] == seen["independent_looks"], (seen, continued)


def test_a_coverage_audit_run_on_one_replica_reaches_the_metrics_of_another(
    postgres_url: str, tmp_path: Path, samples_dir: Path, coco: dict
) -> None:
    settings = {"admin_token": ADMIN_TOKEN, "store_url": postgres_url}
    with LiveServer(tmp_path / "a", **settings) as a, LiveServer(tmp_path / "b", **settings) as b:
        audit = run_audit(a, batch_zip(samples_dir, coco, images=4), epsilon=[0.1])
        assert b.client.get(f"/v1/admin/audits/{audit['id']}", headers=b.admin).status_code == 200
        latest = f'cks_audit_latest_id{{version="1"}} {float(audit["id"])}'
        wait_until(lambda: latest in b.client.get("/metrics").text, "B's gauges show A's audit", timeout=15)
