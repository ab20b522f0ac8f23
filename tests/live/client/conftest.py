"""The client's tests: against the service on a loopback port (``server``, tests/conftest.py: a thread
of the test's process, tests/api/in_process.py OnLoopback), with this checkout's client.

``client/`` goes first on sys.path: the client is its own distribution (``pip install ./client``),
and an installed copy (the server's editable install of another checkout, say) must not stand
in for the code under test, as ``service_env`` puts this checkout first for the servers.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator

import pytest

from service.infra.settings import PACKAGE_ROOT

CLIENT_ROOT = PACKAGE_ROOT / "client"
sys.path.insert(0, str(CLIENT_ROOT))

# The server per module and the bundled samples come from tests/conftest.py.
from tests.api.in_process import OnLoopback  # noqa: E402
from tests.service_calls import ADMIN_TOKEN  # noqa: E402


@pytest.fixture(scope="module")
def admin(server: OnLoopback) -> Iterator[KeypointClient]:  # noqa: F821  (KeypointClient: imported inside)
    """A client with the admin token, for the module's server."""
    from keypoint_client import KeypointClient

    with KeypointClient(server.url, token=ADMIN_TOKEN) as client:
        yield client
