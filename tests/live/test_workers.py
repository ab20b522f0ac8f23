"""`keypoint-service serve` with CKS_WORKERS=2: /metrics sums every worker, and every worker
answers the drift of both (reads in a row no longer flip between the workers' own windows); the
gauges of a worker SIGKILLed mid-request leave the sums.

Each request opens a new connection, so the kernel spreads them over both workers; each
worker's own counter file must show some of them, which is what makes the summed count a
real test of the aggregation.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from prometheus_client.mmap_dict import MmapedDict

from service.infra.metrics import MULTIPROCESS_ENV, metrics_payload
from service.infra.settings import PACKAGE_ROOT
from tests.api.test_audits import run_audit
from tests.live.server import LiveServer, cli, free_port, service_env
from tests.live.test_drift_streams import FRAMES_PER_SCENE
from tests.live.test_replicas import SCENES, drift, send_heavy_scenes
from tests.live.test_replicas import SHARE_S as REPLICA_SHARE_S
from tests.predict_client import instances_of, predict_json, predict_ok
from tests.samples import Sample, batch_zip, samples_by_image
from tests.service_calls import ADMIN_TOKEN, wait_until

REQUESTS = 40
SHARE_S = 1.0  # CKS_DRIFT_SHARE_SECONDS: each worker shares its drift windows this often


@pytest.fixture
def two_workers(tmp_path: Path) -> Iterator[tuple[str, Path]]:
    port = free_port()
    data = tmp_path / "data"
    env = service_env(data, workers=2, port=port, admin_token=ADMIN_TOKEN, drift_share_seconds=SHARE_S)
    with open(tmp_path / "serve.log", "wb") as log:
        process = subprocess.Popen([*cli(), "serve"], env=env, cwd=PACKAGE_ROOT, stdout=log, stderr=log)
    url = f"http://127.0.0.1:{port}"

    def ready() -> bool:
        assert process.poll() is None, (tmp_path / "serve.log").read_text()
        try:
            return httpx.get(f"{url}/readyz", timeout=1).status_code == 200
        except httpx.TransportError:
            return False

    try:
        wait_until(ready, "both workers serve", timeout=60)
        yield url, data
    finally:
        process.send_signal(signal.SIGINT)
        process.wait(timeout=30)
    assert list((data / "metrics").iterdir()) == [], "serve left its metrics folder behind"


def predict_count(text: str) -> float:
    pattern = r'^cks_http_requests_total\{method="POST",route="/v1/predict",status="200"\} ([0-9.e+]+)$'
    match = re.search(pattern, text, re.MULTILINE)
    return float(match.group(1)) if match else 0.0


def worker_predicts(counter_file: Path) -> float:
    """Successful predicts counted in one worker's multiprocess counter file."""
    values = MmapedDict(str(counter_file), read_mode=True)
    try:
        return sum(
            value
            for key, value, _ in values.read_all_values()
            if '"cks_http_requests_total"' in key and '"/v1/predict"' in key and '"200"' in key
        )
    finally:
        values.close()


def test_metrics_sum_over_the_workers(two_workers: tuple[str, Path], samples: list[Sample]) -> None:
    url, data = two_workers
    path, group = next(iter(samples_by_image(samples).items()))
    image, request = path.read_bytes(), {"instances": instances_of(group)}
    for _ in range(REQUESTS):
        with httpx.Client(base_url=url, timeout=60) as client:  # a new connection each time
            assert predict_json(client, image, request).status_code == 200

    (folder,) = (data / "metrics").iterdir()  # one folder per serve process

    def served() -> dict[str, float]:
        return {path.name: worker_predicts(path) for path in folder.glob("counter_*.db")}

    # A request is counted as its middleware finishes, just after its answer was sent.
    wait_until(lambda: sum(served().values()) == REQUESTS, f"{REQUESTS} requests counted")
    assert len(served()) == 2 and all(served().values()), f"both workers must have served: {served()}"
    for _ in range(6):  # whichever worker answers the scrape
        with httpx.Client(base_url=url, timeout=60) as client:
            text = client.get("/metrics").text
        assert predict_count(text) == REQUESTS, text
        assert re.search(r"^cks_predict_in_flight(\{.*\})? 0\.0$", text, re.MULTILINE), text


def test_every_worker_reports_the_windows_of_both(
    two_workers: tuple[str, Path],  # noqa: F811
    samples: list[Sample],
) -> None:
    """Each worker shares its windows through the store (CKS_DRIFT_SHARE_SECONDS): whichever
    answers, the drift report and cks_drift_* cover the values of both."""
    url, _ = two_workers
    path, group = next(iter(samples_by_image(samples).items()))
    image, request = path.read_bytes(), {"instances": instances_of(group)}
    requests, rows = 20, 8 * len(group)
    for _ in range(requests):
        with httpx.Client(base_url=url, timeout=60) as client:  # a new connection each time
            predict_ok(client, image, request)

    def read() -> tuple[dict, str]:
        with httpx.Client(base_url=url, timeout=60) as client:
            report = client.get("/v1/admin/drift", headers={"Authorization": f"Bearer {ADMIN_TOKEN}"}).json()
            return report, client.get("/metrics").text

    wait_until(lambda: read()[0]["recorded"] == requests * rows, "every value shared", timeout=30)
    time.sleep(2 * SHARE_S)  # each worker's last share written, and read by the other
    answered: set[int] = set()
    for _ in range(60):  # until both workers have answered
        report, metrics = read()
        assert (report["recorded"], report["replicas"]) == (requests * rows, 2), report
        assert "cks_drift_window_size{" in metrics and "cks_drift_replicas 2.0" in metrics
        per_worker = re.findall(r'^cks_drift_process_values\{pid="\d+"\} (\S+)$', metrics, re.MULTILINE)
        assert sum(map(float, per_worker)) == requests * rows and len(per_worker) == 2, metrics
        answered.add(report["process"])
        if len(answered) == 2:
            break
    assert len(answered) == 2, answered


def test_with_several_workers_the_gauges_are_the_latest_audits(
    tmp_path: Path, samples_dir: Path, coco: dict
) -> None:
    """Each worker process keeps its own gauge values; the newest audit's must hide the older
    one's, whichever worker ran either (prometheus multiprocess mode, "mostrecent")."""
    with LiveServer(tmp_path / "data", admin_token=ADMIN_TOKEN, workers=2) as live:
        run_audit(live, batch_zip(samples_dir, coco, images=4), epsilon=[0.05])
        latest = run_audit(live, batch_zip(samples_dir, coco, images=4), epsilon=[0.2])

        def shows_only_the_latest() -> bool:  # the job reads succeeded just before its gauges are set
            metrics = live.client.get("/metrics").text
            values = re.findall(r'^cks_audit_coverage\{epsilon="([^"]+)".*\} (\S+)$', metrics, re.MULTILINE)
            return {epsilon for epsilon, value in values if value != "NaN"} == {"0.2"}

        wait_until(shows_only_the_latest, "the latest audit's gauges are published")
        for _ in range(4):  # whichever worker answers
            metrics = live.client.get("/metrics").text
            values = re.findall(r'^cks_audit_coverage\{epsilon="([^"]+)".*\} (\S+)$', metrics, re.MULTILINE)
            assert {epsilon for epsilon, value in values if value != "NaN"} == {"0.2"}
            assert f'cks_audit_latest_id{{version="1"}} {float(latest["id"])}' in metrics


def test_two_workers_answer_the_same_drift(tmp_path: Path) -> None:
    with LiveServer(
        tmp_path / "data", admin_token=ADMIN_TOKEN, workers=2, drift_share_seconds=REPLICA_SHARE_S
    ) as s:
        wait_until(lambda: drift(s.url)["replicas"] == 2, "both workers share their windows", timeout=60)
        send_heavy_scenes([s], SCENES // 2)
        frames = SCENES // 2 * FRAMES_PER_SCENE
        wait_until(lambda: drift(s.url)["frames"] == frames, "every frame counted", timeout=30)
        time.sleep(3 * REPLICA_SHARE_S)  # each worker's last share written and read by the other
        reads = [drift(s.url) for _ in range(12)]
        assert {(r["frames"], r["alarm"], r["independent_looks"], r["replicas"]) for r in reads} == {
            (frames, reads[0]["alarm"], reads[0]["independent_looks"], 2)
        }, [(r["process"], r["frames"], r["alarm"]) for r in reads]
        assert len({r["process"] for r in reads}) == 2, "both workers must have answered"


def test_gauges_of_a_killed_worker_leave_the_multiprocess_sums(tmp_path: Path, monkeypatch) -> None:
    """A worker SIGKILLed while a request was in flight must not leave a permanent offset."""
    env = {**os.environ, MULTIPROCESS_ENV: str(tmp_path)}
    code = (
        "import os, signal, sys\n"
        "from service.infra.metrics import PREDICT_IN_FLIGHT\n"
        "PREDICT_IN_FLIGHT.inc()\n"
        "sys.stdout.write('ready\\n'); sys.stdout.flush()\n"
        "signal.pause()\n"
    )
    worker = subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, text=True)
    assert worker.stdout.readline() == "ready\n"
    monkeypatch.setenv(MULTIPROCESS_ENV, str(tmp_path))
    assert b"cks_predict_in_flight 1.0" in metrics_payload()[0]
    worker.send_signal(signal.SIGKILL)
    worker.wait()
    assert b"cks_predict_in_flight 1.0" not in metrics_payload()[0]  # no live worker: no sample
    assert not list(tmp_path.glob(f"gauge_live*_{worker.pid}.db"))
