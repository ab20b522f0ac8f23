"""The client is typed: it ships py.typed and passes ``mypy --strict``."""

from __future__ import annotations

import subprocess
import sys

from service.infra.settings import PACKAGE_ROOT
from tests.live.client.conftest import CLIENT_ROOT


def test_the_client_passes_mypy_strict() -> None:
    assert (CLIENT_ROOT / "keypoint_client" / "py.typed").is_file()
    command = [sys.executable, "-m", "mypy", "--strict", "client/keypoint_client"]
    result = subprocess.run(command, cwd=PACKAGE_ROOT, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.startswith("Success: no issues found"), result.stdout
