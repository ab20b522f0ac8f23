"""One monitoring truth for the fleet: two server processes on one real PostgreSQL store, shifted
traffic (heavily occluded scenes) sent to replica A only; replica B raises the alarm, its answer
covering both replicas. With CKS_WORKERS=2 the same holds for two workers of one server: reads
in a row no longer flip between the workers' own windows. A coverage audit run on one replica
reaches the gauges of the other.
"""

from __future__ import annotations

import time
from pathlib import Path

import httpx

from tests.api.test_audits import run_audit
from tests.live.server import LiveServer
from tests.live.test_drift_streams import FRAMES_PER_SCENE, send
from tests.samples import batch_zip
from tests.service_calls import ADMIN_TOKEN, wait_until
from tests.streams import render_requests

SHARE_S = 0.5  # CKS_DRIFT_SHARE_SECONDS: short, to keep the test short
SCENES = 60


def drift(url: str) -> dict:
    with httpx.Client(base_url=url, timeout=60) as client:  # a new connection: any worker answers
        response = client.get("/v1/admin/drift", headers={"Authorization": f"Bearer {ADMIN_TOKEN}"})
    assert response.status_code == 200, response.text
    return response.json()


def send_heavy_scenes(servers: list[LiveServer], scenes: int) -> None:
    """Each scene's frames sent to the servers in turn, as a round-robin proxy does."""
    turn = 0
    for scene in range(scenes):
        (views,) = render_requests(9402 + scene, 1, 1, "heavy_occlusion")
        for _ in range(FRAMES_PER_SCENE):
            send(servers[turn % len(servers)], views[0])
            turn += 1


def test_shifted_traffic_to_one_replica_raises_the_alarm_read_from_another(
    postgres_url: str, tmp_path: Path
) -> None:
    settings = {"admin_token": ADMIN_TOKEN, "store_url": postgres_url, "drift_share_seconds": SHARE_S}
    with LiveServer(tmp_path / "a", **settings) as a, LiveServer(tmp_path / "b", **settings) as b:
        send_heavy_scenes([a], SCENES)
        wait_until(lambda: drift(a.url)["alarm"], "replica A's alarm", timeout=30)
        wait_until(lambda: drift(b.url)["alarm"], "replica B raises the alarm of A's traffic", timeout=30)
        frames = SCENES * FRAMES_PER_SCENE
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


def test_two_workers_answer_the_same_drift(tmp_path: Path) -> None:
    with LiveServer(tmp_path / "data", admin_token=ADMIN_TOKEN, workers=2, drift_share_seconds=SHARE_S) as s:
        wait_until(lambda: drift(s.url)["replicas"] == 2, "both workers share their windows", timeout=60)
        send_heavy_scenes([s], SCENES // 2)
        frames = SCENES // 2 * FRAMES_PER_SCENE
        wait_until(lambda: drift(s.url)["frames"] == frames, "every frame counted", timeout=30)
        time.sleep(3 * SHARE_S)  # each worker's last share written and read by the other
        reads = [drift(s.url) for _ in range(12)]
        assert {(r["frames"], r["alarm"], r["independent_looks"], r["replicas"]) for r in reads} == {
            (frames, reads[0]["alarm"], reads[0]["independent_looks"], 2)
        }, [(r["process"], r["frames"], r["alarm"]) for r in reads]
        assert len({r["process"] for r in reads}) == 2, "both workers must have answered"


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
    settings = {"admin_token": ADMIN_TOKEN, "store_url": postgres_url, "store_poll_seconds": 0.5}
    with LiveServer(tmp_path / "a", **settings) as a, LiveServer(tmp_path / "b", **settings) as b:
        audit = run_audit(a, batch_zip(samples_dir, coco, images=4), epsilon=[0.1])
        assert b.client.get(f"/v1/admin/audits/{audit['id']}", headers=b.admin).status_code == 200
        latest = f'cks_audit_latest_id{{version="1"}} {float(audit["id"])}'
        wait_until(lambda: latest in b.client.get("/metrics").text, "B's gauges show A's audit", timeout=15)
