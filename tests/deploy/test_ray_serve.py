"""Ray Serve (service/deploy_ray.py): two replicas on a real local Ray cluster and one PostgreSQL store.

A Ray cluster of the test's own on loopback (``ray.init``), the application deployed on it by
``python -m service.deploy_ray --detach`` with Serve's HTTP proxy on a free port, and a real
SIGKILL. Replicas are told apart by the X-Replica header the deployment adds. The Serve
config file (deploy/ray/serve_config.yaml) is checked without a cluster.
"""

from __future__ import annotations

import importlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
import ray
import yaml
from ray import serve
from ray._private.state import actors  # the GCS actor table: works without Ray's dashboard
from ray.serve import Application
from ray.serve.schema import ServeDeploySchema

from calibration_store import open_store
from service.calibration.registry import POLL_SECONDS
from service.deploy_ray import (
    ADMIN_HEADROOM,
    APP_NAME,
    DEPLOYMENT_NAME,
    REPLICA_HEADER,
    Scaling,
    application,
    build_app,
)
from service.infra.processes import process_folder
from service.infra.settings import PACKAGE_ROOT, Settings
from tests.live.server import free_port, service_env
from tests.predict_client import instances_of, predict_json
from tests.samples import batch_zip, count_instances, load_samples, samples_by_image
from tests.service_calls import ADMIN_TOKEN, BUSY_MACHINE_MARGIN_S, wait_until

SERVE_CONFIG = PACKAGE_ROOT / "deploy" / "ray" / "serve_config.yaml"
REPLICAS = 2
CLIENTS = 3  # clients predicting at once; each has at most one request in flight
POLL_S = POLL_SECONDS  # how often a replica looks for a new version
IMAGES = 4  # images of the calibration batch
SETTINGS = {  # one onnxruntime thread and small admission per replica: two replicas on two cores
    "admin_token": ADMIN_TOKEN,
    "max_concurrent_inferences": 2,
    "max_queued_requests": 2,
}


@dataclass(frozen=True)
class Answer:
    """One predict request as its client saw it."""

    sent: float
    done: float
    status: int | None  # None: no HTTP answer at all
    replica: str | None
    version: int | None  # the calibration version that answered
    error: str = ""


class Service:
    """The application behind Serve's proxy, and the requests the checks need."""

    def __init__(self, url: str, data_dir: Path, image: bytes, parameters: dict) -> None:
        self.url, self.data_dir = url, data_dir
        self._image, self._parameters = image, parameters
        self.client = httpx.Client(base_url=url, timeout=60.0)

    def predict(self, client: httpx.Client | None = None) -> Answer:
        sent = time.monotonic()
        try:
            response = predict_json(client or self.client, self._image, self._parameters)
        except httpx.TransportError as error:
            return Answer(sent, time.monotonic(), None, None, None, repr(error))
        ok = response.status_code == 200
        return Answer(
            sent,
            time.monotonic(),
            response.status_code,
            response.headers.get(REPLICA_HEADER),
            response.json()["calibration"]["version"] if ok else None,
            "" if ok else response.text[:300],
        )

    @contextmanager
    def predicting(self) -> Iterator[list[Answer]]:
        """CLIENTS clients predict in a loop while the block runs; their answers, as they come."""
        answers: list[Answer] = []
        stop = threading.Event()

        def client_loop() -> None:
            with httpx.Client(base_url=self.url, timeout=60.0) as client:
                while not stop.is_set():
                    answers.append(self.predict(client))

        with ThreadPoolExecutor(CLIENTS) as pool:
            clients = [pool.submit(client_loop) for _ in range(CLIENTS)]
            try:
                yield answers
            finally:
                stop.set()
                for client in clients:
                    client.result()
        answers.sort(key=lambda answer: answer.sent)

    def admin(
        self, method: str, path: str, headers: dict[str, str] | None = None, **kwargs: Any
    ) -> httpx.Response:
        headers = {"Authorization": f"Bearer {ADMIN_TOKEN}", **(headers or {})}
        response = self.client.request(method, path, headers=headers, **kwargs)
        assert REPLICA_HEADER in response.headers, response.headers
        return response

    def from_every_replica(
        self, path: str, replicas: set[str], method: str = "GET", status: int = 200, **kwargs: Any
    ) -> dict[str, dict]:
        """Send a request until every replica has answered it with ``status``; each one's body."""
        bodies: dict[str, dict] = {}
        for _ in range(100):
            response = self.admin(method, path, **kwargs)
            assert response.status_code == status, response.text
            bodies[response.headers[REPLICA_HEADER]] = response.json()
            if set(bodies) == replicas:
                return bodies
        raise AssertionError(f"only {sorted(bodies)} of {sorted(replicas)} answered {path} in 100 requests")


def replica_pids() -> dict[str, int]:
    """The deployment's live replicas: X-Replica id -> worker process id."""
    prefix = f"SERVE_REPLICA::{APP_NAME}#{DEPLOYMENT_NAME}#"
    return {
        actor["Name"].removeprefix(prefix): actor["Pid"]
        for actor in actors().values()
        if actor["Name"].startswith(prefix) and actor["State"] == "ALIVE"
    }


def every(seconds: float, condition: Callable[[], bool]) -> Callable[[], bool]:
    """``condition`` checked at most every ``seconds`` by wait_until: each check asks Ray or the service."""

    def paced() -> bool:
        time.sleep(seconds)
        return condition()

    return paced


def healthy_replicas() -> int:
    """Replicas Serve reports running (0 while the application is not running)."""
    application = serve.status().applications[APP_NAME]
    running = application.deployments[DEPLOYMENT_NAME].replica_states.get("RUNNING", 0)
    return running if application.status == "RUNNING" else 0


@pytest.fixture
def service(postgres_url: str, tmp_path: Path, samples_dir: Path, coco: dict) -> Iterator[Service]:
    started = time.monotonic()
    # ray.init leaves variables (RAY_AUTH_MODE, PYTHONBREAKPOINT, ...) and a SIGTERM handler behind
    environ, sigterm = os.environ.copy(), signal.getsignal(signal.SIGTERM)
    # Ray's workers inherit the raylet's environment: they import this checkout's code.
    os.environ["PYTHONPATH"] = service_env(tmp_path)["PYTHONPATH"]
    # Serve's controller gives its HTTP proxy 5 s to report ready, three times, then kills it: on a
    # 2-core machine running the rest of the suite beside it, that start took longer (CI, 12:00).
    os.environ["RAY_SERVE_PROXY_READY_CHECK_TIMEOUT_S"] = "60"
    # A cluster of the test's own ("local": never one found on the machine), on loopback.
    ray.init(address="local", num_cpus=2, include_dashboard=False, _node_ip_address="127.0.0.1")
    try:
        data_dir, port = tmp_path / "data", free_port()  # one data directory: both replicas on one node
        cluster = ["--address", ray.get_runtime_context().gcs_address, "--detach"]
        proxy = ["--host", "127.0.0.1", "--port", str(port)]
        replicas = ["--replicas", str(REPLICAS), "--num-cpus", "0.5"]
        command = [sys.executable, "-m", "service.deploy_ray", *cluster, *proxy, *replicas]
        env = service_env(data_dir, store_url=postgres_url, **SETTINGS)
        run = subprocess.run(command, env=env, cwd=PACKAGE_ROOT, capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stdout + run.stderr
        print(f"\nRay cluster, Serve and {REPLICAS} replicas up: {time.monotonic() - started:.1f} s")
        path, group = next(iter(samples_by_image(load_samples(samples_dir, coco)).items()))
        live = Service(
            f"http://127.0.0.1:{port}", data_dir, path.read_bytes(), {"instances": instances_of(group)}
        )
        yield live
        live.client.close()
    finally:
        stopping = time.monotonic()
        serve.shutdown()
        ray.shutdown()
        os.environ.clear()
        os.environ.update(environ)
        signal.signal(signal.SIGTERM, sigterm)
        print(f"Serve and the Ray cluster shut down: {time.monotonic() - stopping:.1f} s")


@pytest.mark.slow
@pytest.mark.ray
def test_two_replicas_on_one_store(
    service: Service, postgres_url: str, samples_dir: Path, coco: dict
) -> None:
    replicas = predictions_are_answered_by_both_replicas(service)
    batch, instances = batch_zip(samples_dir, coco, IMAGES), count_instances(coco, IMAGES)
    version, receiver = job_submitted_through_one_replica_finishes_once(
        service, replicas, postgres_url, batch, instances
    )
    activation_through_one_replica_is_served_by_all(service, replicas, version)
    every_replica_refuses_a_bad_upload(service, replicas)
    killed_replica_is_replaced(service, version, victim=min(replicas))
    stopped_replicas_close_their_state(service)


def predictions_are_answered_by_both_replicas(service: Service) -> set[str]:
    started = time.monotonic()
    answers = [service.predict() for _ in range(40)]
    assert [a.status for a in answers] == [200] * len(answers), [a.error for a in answers if a.error]
    assert {a.version for a in answers} == {1}, "the bundled calibration, bootstrapped once"
    replicas = set(replica_pids())
    assert len(replicas) == REPLICAS and {a.replica for a in answers} == replicas, (replicas, answers)
    print(f"predictions answered by both replicas: {time.monotonic() - started:.1f} s")
    return replicas


def job_submitted_through_one_replica_finishes_once(
    service: Service, replicas: set[str], postgres_url: str, batch: bytes, instances: int
) -> tuple[int, str]:
    """The new version and the replica that received the upload."""
    started = time.monotonic()
    response = service.admin(
        "POST",
        "/v1/admin/calibrations",
        content=batch,
        params={"note": "via Ray"},
        headers={"Content-Type": "application/zip"},
    )
    assert response.status_code == 202, response.text
    job_id, receiver = response.json()["id"], response.headers[REPLICA_HEADER]
    job_path = f"/v1/admin/jobs/{job_id}"
    # Its row is written before the 202: every replica knows the job from the first poll on.
    for replica, job in service.from_every_replica(job_path, replicas).items():
        assert job["state"] in ("queued", "running", "succeeded"), (replica, job)

    def finished() -> bool:
        return service.admin("GET", job_path).json()["state"] not in ("queued", "running")

    wait_until(every(0.1, finished), f"job {job_id} finished", timeout=120)

    reports = service.from_every_replica(job_path, replicas)
    job = reports[receiver]
    assert all(report == job for report in reports.values()), reports
    assert (job["state"], job["done"], job["total"], job["errors"]) == ("succeeded", instances, instances, [])
    version = job["result"]["version"]
    assert version == 2, job
    for listing in service.from_every_replica("/v1/admin/calibrations", replicas).values():
        assert [v["version"] for v in listing["versions"]] == [1, 2], "the job stored one version"
    with open_store(postgres_url) as store:
        owner = store.get_job(job_id).owner
    assert owner == f"{socket.gethostname()}:{replica_pids()[receiver]}", "the receiving replica ran it"
    print(
        f"job submitted through {receiver}, finished once, same on both: {time.monotonic() - started:.1f} s"
    )
    return version, receiver


def activation_through_one_replica_is_served_by_all(
    service: Service, replicas: set[str], version: int
) -> None:
    response = service.admin(
        "POST",
        f"/v1/admin/calibrations/{version}/activate",
        json={"reason": "a small batch, for the Ray test", "force": True},
    )
    assert response.status_code == 200, response.text
    activated_at = time.monotonic()
    with service.predicting() as answers:
        # Every replica picks it up at its next poll (1 s); how soon is a figure (printed below,
        # and the fleet benchmark's activation spread), not a bound a busy machine may break.
        wait_until(
            lambda: {a.replica for a in list(answers) if a.version == version} == replicas,
            "every replica serving the new version",
            POLL_S + BUSY_MACHINE_MARGIN_S,
        )
        time.sleep(1.0)  # and keeps serving it
    assert [a.status for a in answers] == [200] * len(answers), [a.error for a in answers if a.error]
    switched = {r: min(a.sent for a in answers if a.replica == r and a.version == version) for r in replicas}
    back = [a for a in answers if a.sent > switched[a.replica] and a.version != version]
    assert not back, f"a replica answered with the old version after the new one: {back}"
    old = [a for a in answers if a.version != version]
    last_old = {r: max([a.done - activated_at for a in old if a.replica == r], default=0.0) for r in replicas}
    print(
        f"activation through {response.headers[REPLICA_HEADER]} served by both; the last answers with the"
        f" old version came {', '.join(f'{d:.2f} s' for d in last_old.values())} after it"
    )


def every_replica_refuses_a_bad_upload(service: Service, replicas: set[str]) -> None:
    """A refused upload leaves its replica's (empty) upload folder: both replicas have one now."""
    service.from_every_replica(
        "/v1/admin/calibrations",
        replicas,
        method="POST",
        status=422,
        content=b"not a zip",
        headers={"Content-Type": "application/zip"},
    )
    uploads = service.data_dir / "uploads"
    assert all(process_folder(uploads, pid).is_dir() for pid in replica_pids().values())


def killed_replica_is_replaced(service: Service, version: int, victim: str) -> None:
    before = replica_pids()
    victim_uploads = process_folder(service.data_dir / "uploads", before[victim])

    def replaced() -> bool:
        return healthy_replicas() == REPLICAS and len(replica_pids().keys() - before.keys()) == 1

    with service.predicting() as answers:
        time.sleep(1.0)  # both replicas busy
        os.kill(before[victim], signal.SIGKILL)
        killed_at = time.monotonic()
        wait_until(every(0.2, replaced), "Serve runs a new replica in place of the killed one", timeout=120)
        replaced_after = time.monotonic() - killed_at
        (new,) = replica_pids().keys() - before.keys()
        wait_until(lambda: any(a.replica == new for a in answers), "the new replica answers", timeout=30)
        time.sleep(0.5)
    failed = [a for a in answers if a.status != 200]
    # Only what the killed replica had accepted fails (a request routed to it afterwards is
    # retried by Serve on another replica): at most one per client, each in flight at the kill.
    assert len(failed) <= CLIENTS and all(a.sent < killed_at <= a.done for a in failed), failed
    after = {a.replica for a in answers if a.sent > killed_at and a.status == 200}
    assert after == before.keys() - {victim} | {new}, after
    assert {a.version for a in answers if a.replica == new} == {version}, (
        "the new replica serves the active one"
    )
    assert not victim_uploads.exists(), "the new replica removed the killed one's upload folder"
    print(
        f"SIGKILL of {victim}: {len(failed)} of {len(answers)} predictions failed, all in flight"
        f" ({sorted({a.status or a.error for a in failed})}); replaced by {new} after {replaced_after:.1f} s"
    )


def stopped_replicas_close_their_state(service: Service) -> None:
    started = time.monotonic()
    uploads = service.data_dir / "uploads"
    survivors = [process_folder(uploads, pid) for pid in replica_pids().values()]
    assert any(folder.is_dir() for folder in survivors), "removed only by its replica's ServiceState.close"
    serve.delete(APP_NAME)
    assert list(uploads.iterdir()) == [], "Serve ran the app's lifespan shutdown on every stopping replica"
    print(f"application deleted, replicas closed their state: {time.monotonic() - started:.1f} s")


def test_the_serve_config_builds_the_application(monkeypatch: pytest.MonkeyPatch) -> None:
    config = ServeDeploySchema.model_validate(yaml.safe_load(SERVE_CONFIG.read_text(encoding="utf-8")))
    assert (config.http_options.host, config.http_options.request_timeout_s) == ("0.0.0.0", None)
    (app,) = config.applications
    module, _, name = app.import_path.partition(":")
    assert getattr(importlib.import_module(module), name) is build_app
    env = app.runtime_env["env_vars"]
    assert [key for key in env if key.removeprefix("CKS_").lower() not in Settings.fields()] == []
    for key, value in env.items():  # the builder runs in a Ray task with the application's runtime_env
        monkeypatch.setenv(key, value)
    assert isinstance(build_app(app.args), Application)
    settings = Settings()
    assert Scaling(**app.args).deployment_options(settings) == {
        "num_replicas": 2,
        "max_ongoing_requests": settings.predict.max_concurrent_inferences
        + settings.predict.max_queued_requests
        + ADMIN_HEADROOM,
        "ray_actor_options": {"num_cpus": 1},
    }


def test_autoscaling_aims_at_the_compute_slots_and_the_store_must_be_postgresql() -> None:
    settings = Settings(store_url="sqlite:///tmp/one-node.db", max_concurrent_inferences=3)
    options = Scaling(min_replicas=2, max_replicas=6).deployment_options(settings)
    assert options["autoscaling_config"] == {
        "min_replicas": 2,
        "max_replicas": 6,
        "target_ongoing_requests": 3,
    }
    assert "num_replicas" not in options
    with pytest.raises(ValueError, match="one PostgreSQL store"):
        application(settings, Scaling())
    with pytest.raises(ValueError, match="below min_replicas"):
        Scaling(min_replicas=3, max_replicas=2)
