"""Fixtures for end-to-end tests of the HTTP service (helpers in tests/service/live.py)."""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from playwright.sync_api import Browser, Playwright, sync_playwright

from tests.service.live import ADMIN_TOKEN, LiveServer, Sample, batch_zip, load_samples, model_dir


@pytest.fixture(scope="session")
def model_path() -> Path:
    return model_dir()


@pytest.fixture(scope="session")
def samples_dir(model_path: Path) -> Path:
    return model_path / "samples"


@pytest.fixture(scope="session")
def manifest(model_path: Path) -> dict:
    return json.loads((model_path / "manifest.json").read_text())


@pytest.fixture(scope="session")
def coco(samples_dir: Path) -> dict:
    return json.loads((samples_dir / "annotations.json").read_text())


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    """A server with the bundled calibration active and admin enabled, shared by one test module."""
    with LiveServer(tmp_path_factory.mktemp("server") / "data", admin_token=ADMIN_TOKEN) as live:
        yield live


@pytest.fixture(scope="session")
def samples(samples_dir: Path, coco: dict) -> list[Sample]:
    return load_samples(samples_dir, coco)


@pytest.fixture(scope="session")
def limits(samples_dir: Path, coco: dict) -> dict[str, int]:
    """Small limits for refusal tests, derived from the samples so that valid small batches fit."""
    small_batch = len(batch_zip(samples_dir, coco, images=2))
    upload_bytes = max(1_000_000, 2 * small_batch)
    largest_file = max((samples_dir / image["file_name"]).stat().st_size for image in coco["images"])
    return {
        "max_upload_bytes": upload_bytes,
        "max_upload_uncompressed_bytes": 2 * upload_bytes,
        "max_upload_files": 8,
        "max_image_pixels": max(image["width"] * image["height"] for image in coco["images"]),
        "max_request_bytes": max(300_000, 2 * largest_file),
        "max_instances": 3,
    }


@pytest.fixture(scope="session")
def limited_server(tmp_path_factory: pytest.TempPathFactory, limits: dict[str, int]) -> Iterator[LiveServer]:
    """A server with small request, image and upload limits; refusals must leave it unchanged."""
    data = tmp_path_factory.mktemp("limited") / "data"
    with LiveServer(data, admin_token=ADMIN_TOKEN, **limits) as live:
        yield live


@pytest.fixture(scope="module")
def playwright() -> Iterator[Playwright]:
    """Playwright, for the browser tests (its own browser download is not reachable offline)."""
    with sync_playwright() as driver:
        yield driver


@pytest.fixture(scope="module")
def browser(playwright: Playwright) -> Iterator[Browser]:
    """Debian's Chromium, headless."""
    chromium = shutil.which("chromium")
    assert chromium, "Debian's chromium is not installed: apt-get install chromium (.ci/run does)"
    browser = playwright.chromium.launch(executable_path=chromium, headless=True)
    yield browser
    browser.close()
