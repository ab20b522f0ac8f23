"""A setting that is no longer read, still set by an operator, stops the start-up and says what
replaced it: a value that would be ignored silently is worse than no start."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.cli import main
from service.infra.settings import REMOVED_SETTINGS, RemovedSettings, Settings
from service.serving.app import create_app


def test_a_removed_setting_stops_the_app_naming_what_replaced_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("CKS_CPU_WORKERS", "4")
    monkeypatch.setenv("CKS_CLIENT_NETWORK_IPV4_PREFIX", "24")
    with pytest.raises(RemovedSettings) as refused, TestClient(create_app(Settings(data_dir=tmp_path))):
        pass
    message = str(refused.value)
    assert message.startswith("CKS_CPU_WORKERS is no longer read: the threads for decode, crop and scoring")
    assert "CKS_CLIENT_NETWORK_IPV4_PREFIX is no longer read: a caller is its predict token" in message
    assert message.endswith("Unset them.")


def test_serve_refuses_a_removed_setting_with_exit_status_2(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("CKS_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("CKS_HEADER_READ_TIMEOUT_SECONDS", "10")
    assert main(["serve"]) == 2
    assert "CKS_HEADER_READ_TIMEOUT_SECONDS is no longer read: the proxy" in capsys.readouterr().err


def test_no_removed_setting_is_a_setting_again() -> None:
    current = {f"CKS_{name.upper()}" for name in Settings.fields()}
    assert not current & set(REMOVED_SETTINGS)
    assert len(current) <= 35
