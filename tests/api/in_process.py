"""The service in process, real model and SQLite: its ASGI app started through fastapi's TestClient
(``InProcess``), or served by uvicorn in a thread on a loopback port (``OnLoopback``: a URL for the
client, a browser or a tool; no process of its own)."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient

from service.infra.settings import Settings
from service.serving import container
from service.serving.app import create_app
from service.serving.loopback import served
from tests.samples import model_dir
from tests.service_calls import ServiceCalls

# What a test server process gets too (tests/live/server.py service_env): one inference thread, two
# CPU workers, so that answers and timings do not depend on the machine's cores.
DEFAULTS: dict[str, Any] = {"inference_threads": 1}
# The peer address requests come from: a local caller, as a server process on loopback sees it.
LOOPBACK_PEER = ("127.0.0.1", 50000)


class LogLines(logging.Handler):
    """The service's log records at INFO and above while attached, as lines: what a server logs.

    pytest's handlers on the root logger keep the service from configuring logging in process
    (service/infra/logs.py ensure_logging), which would set these loggers to INFO as a server does.
    """

    LOGGERS = ("service", "calibration_store")

    def __init__(self) -> None:
        super().__init__()
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(f"{record.levelname} {record.name}: {record.getMessage()}")

    def attach(self) -> None:
        self.levels = {name: logging.getLogger(name).level for name in self.LOGGERS}
        for name in self.LOGGERS:
            logging.getLogger(name).setLevel(min(self.levels[name] or logging.INFO, logging.INFO))
            logging.getLogger(name).addHandler(self)

    def detach(self) -> None:
        for name, level in self.levels.items():
            logging.getLogger(name).removeHandler(self)
            logging.getLogger(name).setLevel(level)


@contextmanager
def fixed_values(fixed: dict[str, Any] | None) -> Iterator[None]:
    """Fixed values of ``service.serving.container`` changed (``{"MAX_INSTANCES": 3}``) while a
    service starts, which is when it reads them: small limits that keep a refusal test small.
    Services started after it, while it still runs, get the values as they are."""
    with pytest.MonkeyPatch.context() as patch:
        for name, value in (fixed or {}).items():
            assert hasattr(container, name), f"service.serving.container has no {name}"
            patch.setattr(container, name, value)
        yield


class InProcess(ServiceCalls):
    """The app of ``Settings(data_dir=..., **settings)``, started; ``client`` calls it in process
    (``fixed``: see ``fixed_values``)."""

    def __init__(self, data_dir: Path, fixed: dict[str, Any] | None = None, **settings: Any) -> None:
        self.data_dir = Path(data_dir)
        self.settings = settings
        self.fixed = fixed
        values = {"model_dir": model_dir(), **DEFAULTS, **settings}
        self.app = create_app(Settings(data_dir=self.data_dir, **values))
        self.client = TestClient(self.app, client=LOOPBACK_PEER)
        self.log_lines = LogLines()

    def log(self) -> str:
        """What the process logged since this service started (any service in it, for that time)."""
        return "\n".join(self.log_lines.lines)

    def __enter__(self) -> InProcess:
        self.log_lines.attach()
        with fixed_values(self.fixed):
            self.client.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.client.__exit__(*exc)
        self.log_lines.detach()


class OnLoopback(ServiceCalls):
    """The service of ``Settings(data_dir=..., **settings)`` served on a free loopback port by a
    thread of this process, as ``keypoint-service predict`` serves it; ``url`` and ``client`` reach it."""

    def __init__(self, data_dir: Path, fixed: dict[str, Any] | None = None, **settings: Any) -> None:
        self.data_dir = Path(data_dir)
        self.settings = settings
        values = {"model_dir": model_dir(), **DEFAULTS, **settings}
        self.service_settings = Settings(data_dir=self.data_dir, **values)
        self.log_lines = LogLines()
        self.stack = ExitStack()
        self.fixed = fixed

    def log(self) -> str:
        """What the process logged since this service started (any service in it, for that time)."""
        return "\n".join(self.log_lines.lines)

    def __enter__(self) -> OnLoopback:
        self.log_lines.attach()
        self.stack.callback(self.log_lines.detach)
        with fixed_values(self.fixed):
            self.url = self.stack.enter_context(served(self.service_settings))
        self.client = self.stack.enter_context(httpx.Client(base_url=self.url, timeout=60.0))
        return self

    def __exit__(self, *exc: object) -> None:
        self.stack.close()
