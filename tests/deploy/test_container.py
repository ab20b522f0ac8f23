"""The repository's Dockerfile, built unchanged with buildah and run with no engine.

The image serves the README's request with the same JSON as the service outside it, as
a non-root user, is ready within its HEALTHCHECK's start period, keeps an activated
calibration in its /data volume across a restart, and stays under a size budget.
Run alone with ``python -m pytest -m container``; deselect with ``-m "not container"``.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service.infra.settings import PACKAGE_ROOT
from tests.deploy.buildah import Container, build, image_bytes, image_config, missing_tools, process_uid
from tests.live.server import LiveServer, free_port
from tests.readme import predict_example
from tests.samples import batch_zip
from tests.service_calls import ADMIN_TOKEN

pytestmark = [pytest.mark.container, pytest.mark.slow]

TAG = "localhost/keypoint-service:test"
# Measured 677 MB on the stand-in bases (Debian's python3 in /usr instead of the official
# images' CPython in /usr/local; the official slim base is ~130 MB, the stand-in ~300 MB).
IMAGE_BUDGET_BYTES = 800 * 10**6
APP_UID = 10001  # the Dockerfile's `useradd --uid`


@pytest.fixture(scope="module")
def image() -> str:
    missing = missing_tools()
    assert not missing, f"{missing} not installed: apt-get install buildah debootstrap (.ci/run does)"
    build(PACKAGE_ROOT, TAG)
    print(f"\nimage {TAG}: {image_bytes(TAG) / 1e6:.0f} MB (budget {IMAGE_BUDGET_BYTES / 1e6:.0f} MB)")
    return TAG


def predict(url: str, image: Path, request: dict) -> dict:
    files = {"image": (image.name, image.read_bytes(), "image/jpeg"), "request": (None, json.dumps(request))}
    response = httpx.post(f"{url}/v1/predict", files=files, timeout=60)
    assert response.status_code == 200, response.text
    return response.json()


def assert_same_json(expected: object, actual: object, where: str = "$") -> None:
    """Equal structure and values; floats within 1e-9 (the image may carry other numpy builds)."""
    if isinstance(expected, dict):
        assert isinstance(actual, dict) and expected.keys() == actual.keys(), where
        for key in expected:
            assert_same_json(expected[key], actual[key], f"{where}.{key}")
    elif isinstance(expected, list):
        assert isinstance(actual, list) and len(expected) == len(actual), where
        for i, (e, a) in enumerate(zip(expected, actual, strict=True)):
            assert_same_json(e, a, f"{where}[{i}]")
    elif isinstance(expected, float):
        assert actual == pytest.approx(expected, rel=1e-9, abs=1e-9), where
    else:
        assert expected == actual, where


def wait_ready(url: str, within: float) -> float:
    """Seconds until /readyz answers 200; fails after ``within``."""
    start = time.monotonic()
    while time.monotonic() - start < within:
        try:
            if httpx.get(f"{url}/readyz", timeout=2).status_code == 200:
                return time.monotonic() - start
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    raise AssertionError(f"/readyz not 200 within {within} s")


def start_period_s(tag: str) -> float:
    """The HEALTHCHECK's start period, in seconds."""
    return image_config(tag)["Healthcheck"]["StartPeriod"] / 1e9


@pytest.fixture
def data_dir(tmp_path: Path) -> Iterator[Path]:
    data = tmp_path / "data"
    data.mkdir()
    os.chown(data, APP_UID, APP_UID)  # the volume must be writable by the image's user
    yield data


def test_the_image_is_lean_and_declares_its_contract(image: str) -> None:
    assert image_bytes(image) < IMAGE_BUDGET_BYTES
    config = image_config(image)
    assert config["User"] == "app"
    assert "/data" in config["Volumes"] and "8000/tcp" in config["ExposedPorts"]
    assert config["Cmd"] == ["keypoint-service", "serve"]
    assert start_period_s(image) == 30


def test_the_container_serves_like_the_service_and_keeps_its_calibrations(
    image: str, data_dir: Path, tmp_path: Path, samples_dir: Path, coco: dict
) -> None:
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = {"CKS_PORT": str(port), "CKS_ADMIN_TOKEN": ADMIN_TOKEN}
    log = tmp_path / "container.log"
    admin = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    image_path, request, _ = predict_example()

    container = Container(image, data_dir, env, log)
    try:
        ready_after = wait_ready(url, start_period_s(image))
        print(f"\n/readyz 200 after {ready_after:.1f} s")
        assert process_uid(container.served_pid()) == APP_UID
        inside = predict(url, image_path, request)
        with LiveServer(tmp_path / "outside") as outside:
            assert_same_json(predict(outside.url, image_path, request), inside)

        body = batch_zip(samples_dir, coco, images=4)
        response = httpx.post(
            f"{url}/v1/admin/calibrations",
            content=body,
            timeout=60,
            params={"activate": "true", "force": "true", "reason": "container test"},
            headers={**admin, "Content-Type": "application/zip"},
        )
        assert response.status_code == 202, response.text
        job = response.json()
        deadline = time.monotonic() + 120
        while job["state"] not in ("succeeded", "failed", "interrupted") and time.monotonic() < deadline:
            time.sleep(0.2)
            job = httpx.get(f"{url}/v1/admin/jobs/{job['id']}", headers=admin, timeout=10).json()
        assert job["state"] == "succeeded", job
        assert httpx.get(f"{url}/readyz", timeout=5).json()["active_calibration"] == 2
    finally:
        container.stop()
    assert "Application shutdown complete" in log.read_text(), "SIGTERM did not stop it gracefully"
    assert (data_dir / "calibrations.db").is_file(), "the store is not in the /data volume"

    restarted = Container(image, data_dir, env, log)
    try:
        wait_ready(url, start_period_s(image))
        assert httpx.get(f"{url}/readyz", timeout=5).json()["active_calibration"] == 2
        versions = httpx.get(f"{url}/v1/admin/calibrations", headers=admin, timeout=10).json()["versions"]
        assert [v["version"] for v in versions] == [1, 2]
    finally:
        restarted.stop()

    fast = Container(image, data_dir, {**env, "CKS_MODEL_DIR": "/app/models/lmo-synth-unet-int8"}, log)
    try:  # the bundled int8 variant, one setting away, beside the other's versions on the volume
        wait_ready(url, start_period_s(image))
        answer = predict(url, image_path, request)
        assert answer["model"]["variant"] == "int8"
        assert httpx.get(f"{url}/readyz", timeout=5).json()["active_calibration"] == 1
    finally:
        fast.stop()
