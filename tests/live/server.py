"""Helpers for end-to-end tests of the HTTP service: real uvicorn processes on loopback ports.

``LiveServer`` starts the server the way production does (``keypoint-service serve``, run
as ``python -m service.cli serve`` so that this checkout's code is served) with a given
environment (a temporary data directory, an admin token, optionally a PostgreSQL store URL,
the model directory from ``Settings().model.directory``), waits for ``/healthz`` and stops the
process with SIGTERM at teardown. Its admin conveniences are tests/service_calls.py's, shared
with the in-process service of tests/api.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx

from benchmarks import load
from service.infra.settings import PACKAGE_ROOT, Settings
from tests.samples import model_dir
from tests.service_calls import ServiceCalls

STARTUP_TIMEOUT_S = 60.0


def metric(server: LiveServer, name: str, labels: str = "") -> float:
    """A sample of the server's /metrics (0 when absent)."""
    return load.metric(server.url, name, labels)


def read_until_closed(connection: socket.socket) -> str:
    """Everything the server sends until it closes the connection (header and body may be split)."""
    received = b""
    while chunk := connection.recv(65536):
        received += chunk
    return received.decode()


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def service_env(data_dir: Path, **settings: Any) -> dict[str, str]:
    """The parent environment without any CKS_* variable, plus the model, data dir and ``settings``.

    ``PYTHONPATH`` starts with this checkout and its client: an installed console script
    (``cli()``) would otherwise import the code of wherever the package was installed from,
    e.g. another worktree.

    ``settings`` keys are setting names (``admin_token="x"`` -> ``CKS_ADMIN_TOKEN=x``); None drops one.
    """
    env = {k: v for k, v in os.environ.items() if not k.startswith("CKS_")}
    env["CKS_MODEL_DIR"] = str(model_dir())
    env["CKS_DATA_DIR"] = str(data_dir)
    env["CKS_WORKERS"] = "1"  # one process unless a test asks for more (test_workers)
    env["CKS_INFERENCE_THREADS"] = "1"
    env["PYTHONUNBUFFERED"] = "1"
    env["PYTHONPATH"] = os.pathsep.join(
        filter(None, [str(PACKAGE_ROOT), str(PACKAGE_ROOT / "client"), os.environ.get("PYTHONPATH")])
    )
    for key, value in settings.items():
        if value is not None:
            env[f"CKS_{key.upper()}"] = str(value)
    return env


class LiveServer(ServiceCalls):
    """One ``keypoint-service serve`` process on a free loopback port; ``fixed`` changes fixed values
    of ``service.serving.container`` in it (tests/live/fixed_serve.py)."""

    def __init__(self, data_dir: Path, fixed: dict[str, Any] | None = None, **settings: Any) -> None:
        self.fixed = fixed
        self.data_dir = Path(data_dir)
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.settings = settings
        self.env = service_env(self.data_dir, **settings)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = self.data_dir.parent / f"{self.data_dir.name}-server-{self.port}.log"
        self.process: subprocess.Popen | None = None
        self.client = httpx.Client(base_url=self.url, timeout=60.0)

    def log(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except FileNotFoundError:
            return ""

    def start(self) -> LiveServer:
        launcher = ["tests.live.fixed_serve", json.dumps(self.fixed)] if self.fixed else ["service.cli"]
        command = [
            sys.executable,
            "-m",
            *launcher,
            "serve",
            "--host",
            "127.0.0.1",
            "--port",
            str(self.port),
        ]
        with open(self.log_path, "wb") as log:
            self.process = subprocess.Popen(
                command, env=self.env, cwd=PACKAGE_ROOT, stdout=log, stderr=subprocess.STDOUT
            )
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                code = self.process.returncode
                raise RuntimeError(f"the server exited with code {code} during start-up; log:\n{self.log()}")
            try:
                if self.client.get("/healthz", timeout=1.0).status_code == 200:
                    return self
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        self.stop()
        raise RuntimeError(
            f"the server did not answer /healthz within {STARTUP_TIMEOUT_S} s; log:\n{self.log()}"
        )

    def stop(self) -> None:
        """SIGTERM, then SIGKILL if the process outlives its shutdown grace period by 10 s."""
        self.client.close()
        if self.process is None or self.process.poll() is not None:
            return
        self.process.terminate()
        default = Settings.fields()["shutdown_grace_seconds"].default
        grace = float(self.env.get("CKS_SHUTDOWN_GRACE_SECONDS", default))
        try:
            self.process.wait(timeout=grace + 10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait(timeout=5)

    def __enter__(self) -> LiveServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def cli() -> list[str]:
    """The installed ``keypoint-service`` entry point (next to this Python, or on PATH)."""
    beside = Path(sys.executable).parent / "keypoint-service"
    found = str(beside) if beside.is_file() else shutil.which("keypoint-service")
    assert found, "the keypoint-service command is not installed: pip install -e '.[test]'"
    return [found]
