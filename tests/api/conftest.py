"""The service in process: its ASGI app through fastapi's TestClient, with the real model and SQLite.

``api`` (admin enabled, the bundled calibration active) is shared by a test module, as a server
process used to be; ``limited_api`` (small request, image and upload limits, which refusals must
leave unchanged) by the session; ``make_api(**settings)`` starts one for a test alone.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.settings import Settings
from tests.samples import model_dir
from tests.service_calls import ADMIN_TOKEN, ServiceCalls

# What a test server process gets too (tests/live/server.py service_env): one inference thread, two
# CPU workers, so that answers and timings do not depend on the machine's cores.
DEFAULTS: dict[str, Any] = {"inference_threads": 1, "cpu_workers": 2}


class InProcessService(ServiceCalls):
    """The app of ``Settings(data_dir=..., **settings)``, started; ``client`` calls it in process."""

    def __init__(self, data_dir: Path, **settings: Any) -> None:
        self.data_dir = Path(data_dir)
        self.settings = settings
        values = {"model_dir": model_dir(), **DEFAULTS, **settings}
        self.app = create_app(Settings(data_dir=self.data_dir, **values))
        self.client = TestClient(self.app)

    def __enter__(self) -> InProcessService:
        self.client.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.client.__exit__(*exc)


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[InProcessService]:
    """The bundled calibration active and admin enabled, shared by one test module."""
    with InProcessService(tmp_path_factory.mktemp("api") / "data", admin_token=ADMIN_TOKEN) as service:
        yield service


@pytest.fixture(scope="session")
def limited_api(
    tmp_path_factory: pytest.TempPathFactory, limits: dict[str, int]
) -> Iterator[InProcessService]:
    """Small request, image and upload limits; refusals must leave it unchanged."""
    data = tmp_path_factory.mktemp("limited") / "data"
    with InProcessService(data, admin_token=ADMIN_TOKEN, **limits) as service:
        yield service


@pytest.fixture
def make_api(tmp_path: Path) -> Iterator[Callable[..., InProcessService]]:
    """Start a service with these settings for this test alone (on ``data_dir`` if given)."""
    started: list[InProcessService] = []

    def make(data_dir: Path | None = None, **settings: Any) -> InProcessService:
        data = data_dir or tmp_path / f"data-{len(started)}"
        started.append(InProcessService(data, **settings).__enter__())
        return started[-1]

    yield make
    for service in reversed(started):
        service.__exit__(None, None, None)
