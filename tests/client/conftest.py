"""The client's tests: against real servers (tests/service/live.py), with this checkout's client.

``client/`` goes first on sys.path: the client is its own distribution (``pip install ./client``),
and an installed copy (the server's editable install of another checkout, say) must not stand
in for the code under test, as ``service_env`` puts this checkout first for the servers.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator

import pytest

from service.runtime.settings import PACKAGE_ROOT

CLIENT_ROOT = PACKAGE_ROOT / "client"
sys.path.insert(0, str(CLIENT_ROOT))

# The shared fixtures of the service's end-to-end tests: a server per module, the bundled samples.
from tests.service.conftest import coco, model_path, samples, samples_dir, server  # noqa: E402, F401
from tests.service.live import ADMIN_TOKEN, LiveServer  # noqa: E402


@pytest.fixture(scope="module")
def admin(server: LiveServer) -> Iterator[KeypointClient]:  # noqa: F811, F821  (server: the fixture above)
    """A client with the admin token, for the module's server."""
    from keypoint_client import KeypointClient

    with KeypointClient(server.url, token=ADMIN_TOKEN) as client:
        yield client
