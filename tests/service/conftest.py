"""Fixtures for end-to-end tests of the HTTP service (helpers in tests/service/live.py)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.service.live import ADMIN_TOKEN, LiveServer, Sample, load_samples, model_dir


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
