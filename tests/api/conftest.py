"""The service in process: its ASGI app through fastapi's TestClient, with the real model and SQLite.

``api`` (admin enabled, the bundled calibration active) is shared by a test module, as a server
process used to be; ``limited_api`` (small request, image and upload limits, which refusals must
leave unchanged) by the session. A test that needs other settings starts its own ``InProcess``.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.api.in_process import InProcess
from tests.service_calls import ADMIN_TOKEN


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[InProcess]:
    """The bundled calibration active and admin enabled, shared by one test module."""
    with InProcess(tmp_path_factory.mktemp("api") / "data", admin_token=ADMIN_TOKEN) as service:
        yield service


@pytest.fixture(scope="session")
def limited_api(
    tmp_path_factory: pytest.TempPathFactory, limits: dict[str, int], fixed_limits: dict[str, int]
) -> Iterator[InProcess]:
    """Small request, image and upload limits; refusals must leave it unchanged."""
    data = tmp_path_factory.mktemp("limited") / "data"
    with InProcess(data, fixed_limits, admin_token=ADMIN_TOKEN, **limits) as service:
        yield service
