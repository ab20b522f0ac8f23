"""Helpers for end-to-end tests of the HTTP service: real uvicorn processes on loopback ports.

``LiveServer`` starts the server the way production does (``keypoint-service serve``, run
as ``python -m service.cli serve`` so that this checkout's code is served) with a given
environment (a temporary data directory, an admin token, optionally a PostgreSQL store URL,
the model directory from ``Settings().model.model_dir``), waits for ``/healthz`` and stops the
process with SIGTERM at teardown. Helpers build COCO-keypoints batch zips from the model's
bundled samples, optionally mutated, for the calibration upload tests.
"""

from __future__ import annotations

import base64
import copy
import io
import json
import os
import shutil
import socket
import subprocess
import sys
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

from benchmarks import faults_clients
from service.runtime.settings import PACKAGE_ROOT, Settings

ADMIN_TOKEN = "test-admin-token"
STARTUP_TIMEOUT_S = 30.0
PROBLEM_JSON = "application/problem+json"


def wait_until(condition: Callable[[], bool], what: str = "condition", timeout: float = 30.0) -> None:
    """Poll ``condition`` every 10 ms; fail naming ``what`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out after {timeout} s waiting until {what}"
        time.sleep(0.01)


def metric(server: LiveServer, name: str, labels: str = "") -> float:
    """A sample of the server's /metrics (0 when absent)."""
    return faults_clients.metric(server.url, name, labels)


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


def model_dir() -> Path:
    """The served model: CKS_MODEL_DIR, or the bundled one (never written to)."""
    return Path(Settings().model.model_dir).resolve()


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
    env["CKS_CPU_WORKERS"] = "2"
    env["PYTHONUNBUFFERED"] = "1"
    env["PYTHONPATH"] = os.pathsep.join(
        filter(None, [str(PACKAGE_ROOT), str(PACKAGE_ROOT / "client"), os.environ.get("PYTHONPATH")])
    )
    for key, value in settings.items():
        if value is not None:
            env[f"CKS_{key.upper()}"] = str(value)
    return env


class LiveServer:
    """One ``keypoint-service serve`` process on a free loopback port."""

    def __init__(self, data_dir: Path, **settings: Any) -> None:
        self.data_dir = Path(data_dir)
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.settings = settings
        self.env = service_env(self.data_dir, **settings)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = self.data_dir.parent / f"{self.data_dir.name}-server-{self.port}.log"
        self.process: subprocess.Popen | None = None
        self.client = httpx.Client(base_url=self.url, timeout=60.0)

    @property
    def admin_token(self) -> str | None:
        return self.settings.get("admin_token")

    @property
    def admin(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.admin_token}"}

    @property
    def uploads_dir(self) -> Path:
        return self.data_dir / "uploads"

    def upload_workspaces(self) -> list[Path]:
        """Upload workspaces left under the uploads folder (one folder per server process)."""
        return sorted(self.uploads_dir.glob("*/*"))

    def log(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except FileNotFoundError:
            return ""

    def start(self) -> LiveServer:
        command = [sys.executable, "-m", "service.cli", "serve", "--host", "127.0.0.1",
                   "--port", str(self.port)]  # fmt: skip
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

    # ------------------------------------------------------------ admin helpers

    def versions(self) -> list[int]:
        response = self.client.get("/v1/admin/calibrations", headers=self.admin)
        assert response.status_code == 200, response.text
        return [v["version"] for v in response.json()["versions"]]

    def upload(self, body: bytes, content_type: str = "application/zip", **params: Any) -> httpx.Response:
        params = {k: (str(v).lower() if isinstance(v, bool) else v) for k, v in params.items()}
        return self.client.post(
            "/v1/admin/calibrations",
            content=body,
            params=params,
            headers={**self.admin, "Content-Type": content_type},
        )

    def job(self, job_id: str) -> dict:
        """GET one job (must answer 200)."""
        response = self.client.get(f"/v1/admin/jobs/{job_id}", headers=self.admin)
        assert response.status_code == 200, f"{self.url}: {response.text}"
        return response.json()

    def wait_job(self, job_id: str, timeout: float = 120.0) -> dict:
        """Poll a job until it succeeds or fails; returns the final job body."""
        deadline = time.monotonic() + timeout
        while True:
            response = self.client.get(f"/v1/admin/jobs/{job_id}", headers=self.admin)
            assert response.status_code == 200, response.text
            job = response.json()
            if job["state"] in ("succeeded", "failed", "interrupted"):
                return job
            assert time.monotonic() < deadline, f"job {job_id} still {job['state']} after {timeout} s: {job}"
            time.sleep(0.1)

    def calibrate(self, body: bytes, **params: Any) -> dict:
        """Upload a batch, wait for its job and require success; returns the job."""
        response = self.upload(body, **params)
        assert response.status_code == 202, response.text
        job = self.wait_job(response.json()["id"])
        assert job["state"] == "succeeded", job
        return job


# ---------------------------------------------------------------- samples and batches


@dataclass(frozen=True)
class Sample:
    """One labeled instance of the bundled samples."""

    image_path: Path
    width: int
    height: int
    object: str
    bbox: list[float]
    keypoints: list[tuple[float, float, int]]  # x, y, v (v = 0: not labeled)


def load_samples(samples_dir: Path, doc: dict) -> list[Sample]:
    images = {image["id"]: image for image in doc["images"]}
    categories = {c["id"]: c["name"] for c in doc["categories"]}
    samples = []
    for ann in doc["annotations"]:
        image = images[ann["image_id"]]
        flat = ann["keypoints"]
        triples = [(flat[i], flat[i + 1], int(flat[i + 2])) for i in range(0, len(flat), 3)]
        samples.append(
            Sample(
                samples_dir / image["file_name"],
                image["width"],
                image["height"],
                categories[ann["category_id"]],
                list(ann["bbox"]),
                triples,
            )  # fmt: skip
        )
    return samples


def samples_by_image(samples: list[Sample]) -> dict[Path, list[Sample]]:
    grouped: dict[Path, list[Sample]] = {}
    for sample in samples:
        grouped.setdefault(sample.image_path, []).append(sample)
    return grouped


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


Mutation = Callable[[dict, dict[str, bytes]], None]


def batch_files(samples_dir: Path, doc: dict, images: int | None = None) -> tuple[dict, dict[str, bytes]]:
    """annotations.json (as a dict) and the image files of the first ``images`` images."""
    doc = copy.deepcopy(doc)
    if images is not None:
        doc["images"] = doc["images"][:images]
        kept = {image["id"] for image in doc["images"]}
        doc["annotations"] = [a for a in doc["annotations"] if a["image_id"] in kept]
    files = {image["file_name"]: (samples_dir / image["file_name"]).read_bytes() for image in doc["images"]}
    return doc, files


def build_zip(
    doc: dict | bytes,
    files: dict[str, bytes],
    *,
    compression: int = zipfile.ZIP_DEFLATED,
    links: dict[str, str] | None = None,
) -> bytes:
    """A zip with annotations.json (a dict, or raw bytes as given), ``files`` and symlink entries."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=compression) as archive:
        raw = doc if isinstance(doc, bytes) else json.dumps(doc).encode()
        archive.writestr("annotations.json", raw)
        for name, data in files.items():
            archive.writestr(name, data)
        for name, target in (links or {}).items():
            info = zipfile.ZipInfo(name)
            info.create_system = 3  # unix, so external_attr carries the file type
            info.external_attr = (0o120777 << 16) & 0xFFFF0000  # S_IFLNK | 0777
            archive.writestr(info, target)
    return buffer.getvalue()


def batch_zip(
    samples_dir: Path, doc: dict, images: int | None = None, mutate: Mutation | None = None
) -> bytes:
    """A zip of the samples' COCO batch (the first ``images`` images), optionally mutated in place."""
    doc, files = batch_files(samples_dir, doc, images)
    if mutate is not None:
        mutate(doc, files)
    return build_zip(doc, files)


def count_instances(doc: dict, images: int | None = None) -> int:
    kept = {image["id"] for image in (doc["images"] if images is None else doc["images"][:images])}
    return sum(1 for a in doc["annotations"] if a["image_id"] in kept)


def assert_problem(response: httpx.Response, status: int, *fragments: str) -> dict:
    """An RFC 9457 problem with this status whose detail (or errors) mentions every fragment."""
    assert response.status_code == status, f"expected {status}, got {response.status_code}: {response.text}"
    assert response.headers["content-type"].startswith(PROBLEM_JSON), response.headers
    body = response.json()
    assert body["status"] == status, body
    assert isinstance(body["title"], str) and body["title"], body
    assert isinstance(body["detail"], str) and body["detail"], body
    text = " ".join([body["detail"], *map(str, body.get("errors", []))]).lower()
    for fragment in fragments:
        assert fragment.lower() in text, f"{fragment!r} not in the problem: {body}"
    return body


def cli() -> list[str]:
    """The installed ``keypoint-service`` entry point (next to this Python, or on PATH)."""
    beside = Path(sys.executable).parent / "keypoint-service"
    found = str(beside) if beside.is_file() else shutil.which("keypoint-service")
    assert found, "the keypoint-service command is not installed: pip install -e '.[test]'"
    return [found]
