"""Shared fixtures: the bundled model's samples, PostgreSQL, and a server process.

The samples: the model directory, its manifest, the COCO annotations, every labeled instance
(``samples``), one image with its instances (``sample``) and small limits that valid small batches
fit (``limits``). PostgreSQL: a throwaway cluster per session, a fresh database per test; tests
request `postgres_url` (a postgresql:// URL of an empty database) or `postgres_cluster`
(tests.postgres_cluster.PostgresCluster). ``server``: the service on a loopback port, served by a
thread of the test's process (tests/api/in_process.py OnLoopback), for the tests that need a URL
(the client, the command line, a browser); a test whose point is a process starts a LiveServer.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.api.in_process import OnLoopback
from tests.postgres_cluster import PostgresCluster
from tests.predict_client import instances_of
from tests.samples import Sample, batch_zip, load_samples, model_dir, samples_by_image
from tests.service_calls import ADMIN_TOKEN

# Which test files start a process, and the few that may (tests/process_starts.py).
pytest_plugins = ["tests.process_starts", "pytester"]


def pytest_configure(config: pytest.Config) -> None:
    """Each test worker (pytest-xdist) keeps to one core, and so do the servers it starts: four
    workers share two cores without a lone request's runs spinning on cores others need (the
    wide path has its own test, tests/unit/detector/test_runtime.py)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if worker:
        cores = sorted(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cores[int(worker.removeprefix("gw")) % len(cores)]})


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


@pytest.fixture(scope="session")
def samples(samples_dir: Path, coco: dict) -> list[Sample]:
    return load_samples(samples_dir, coco)


@pytest.fixture(scope="session")
def sample(samples: list[Sample]) -> tuple[bytes, list[dict]]:
    """The first sample JPEG and its labeled instances."""
    path, group = next(iter(samples_by_image(samples).items()))
    return path.read_bytes(), instances_of(group)


@pytest.fixture(scope="session")
def limits(samples_dir: Path, coco: dict) -> dict[str, int]:
    """Small limits for refusal tests, derived from the samples so that valid small batches fit."""
    small_batch = len(batch_zip(samples_dir, coco, images=2))
    upload_bytes = max(1_000_000, 2 * small_batch)
    largest_file = max((samples_dir / image["file_name"]).stat().st_size for image in coco["images"])
    return {
        "max_upload_bytes": upload_bytes,
        "max_image_pixels": max(image["width"] * image["height"] for image in coco["images"]),
        "max_request_bytes": max(300_000, 2 * largest_file),
    }


@pytest.fixture(scope="session")
def fixed_limits() -> dict[str, int]:
    """Small fixed limits of the service (service.serving.container) for refusal tests."""
    return {"MAX_INSTANCES": 3}


@pytest.fixture(scope="session")
def postgres_cluster() -> Iterator[PostgresCluster]:
    """A PostgreSQL server started from the machine's binaries; fails loudly if absent."""
    cluster = PostgresCluster.start()
    try:
        yield cluster
    finally:
        cluster.stop()


@pytest.fixture
def postgres_url(postgres_cluster: PostgresCluster) -> Iterator[str]:
    """URL of a fresh, empty database, dropped after the test."""
    url = postgres_cluster.create_database()
    yield url
    postgres_cluster.drop_database(url.rsplit("/", 1)[1])


@pytest.fixture(params=["sqlite", "postgres"])
def store_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """URL of an empty store of each backend: a SQLite file, a real PostgreSQL database."""
    if request.param == "sqlite":
        return f"sqlite://{tmp_path}/data/calibration.db"
    return request.getfixturevalue("postgres_url")


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[OnLoopback]:
    """The bundled calibration active and admin enabled, on a loopback URL, shared by one test module."""
    with OnLoopback(tmp_path_factory.mktemp("server") / "data", admin_token=ADMIN_TOKEN) as served:
        yield served
