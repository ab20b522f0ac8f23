"""Server processes (tests/live/server.py): one per test module where the process is shared."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.live.server import LiveServer
from tests.service_calls import ADMIN_TOKEN


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    """A server with the bundled calibration active and admin enabled, shared by one test module."""
    with LiveServer(tmp_path_factory.mktemp("server") / "data", admin_token=ADMIN_TOKEN) as live:
        yield live
