"""The client is typed: it ships py.typed and passes ``mypy --strict``."""

from __future__ import annotations

from mypy import api

from tests.live.client.conftest import CLIENT_ROOT


def test_the_client_passes_mypy_strict() -> None:
    assert (CLIENT_ROOT / "keypoint_client" / "py.typed").is_file()
    stdout, stderr, status = api.run(["--strict", str(CLIENT_ROOT / "keypoint_client")])  # in process
    assert status == 0, stdout + stderr
    assert stdout.startswith("Success: no issues found"), stdout
