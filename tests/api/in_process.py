"""The service in process: its ASGI app started through fastapi's TestClient, real model and SQLite."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient

from service.api.app import create_app
from service.settings import Settings
from tests.samples import model_dir
from tests.service_calls import ServiceCalls

# What a test server process gets too (tests/live/server.py service_env): one inference thread, two
# CPU workers, so that answers and timings do not depend on the machine's cores.
DEFAULTS: dict[str, Any] = {"inference_threads": 1, "cpu_workers": 2}


class InProcess(ServiceCalls):
    """The app of ``Settings(data_dir=..., **settings)``, started; ``client`` calls it in process."""

    def __init__(self, data_dir: Path, **settings: Any) -> None:
        self.data_dir = Path(data_dir)
        self.settings = settings
        values = {"model_dir": model_dir(), **DEFAULTS, **settings}
        self.app = create_app(Settings(data_dir=self.data_dir, **values))
        self.client = TestClient(self.app)

    def __enter__(self) -> InProcess:
        self.client.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.client.__exit__(*exc)
