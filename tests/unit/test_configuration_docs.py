"""The README's settings table is the one the fields make, and every setting is read from its
``CKS_`` variable whatever its group."""

from __future__ import annotations

import pytest

from service.infra.settings import README, Settings, readme_with_table


def test_the_readme_settings_table_is_made_from_the_fields():
    text = README.read_text(encoding="utf-8")
    assert readme_with_table(text) == text, "run python -m service.infra.settings to write the table anew"
    missing = [name for name in Settings.fields() if f"| `CKS_{name.upper()}` |" not in text]
    assert not missing


def test_every_setting_has_a_description():
    undocumented = [name for name, field in Settings.fields().items() if not field.description]
    assert not undocumented, f"give these settings a Field(description=...): {undocumented}"


def test_settings_are_read_from_prefixed_environment(monkeypatch):
    monkeypatch.setenv("CKS_MAX_QUEUED_REQUESTS", "7")
    monkeypatch.setenv("CKS_STORE_URL", "sqlite:////tmp/x.db")
    monkeypatch.setenv("CKS_LOG_LEVEL", "debug")
    settings = Settings(max_upload_bytes=9)
    assert settings.predict.max_queued_requests == 7
    assert settings.storage.resolved_url == "sqlite:////tmp/x.db"
    assert settings.logs.level == "DEBUG"
    assert settings.calibration.max_upload_bytes == 9


def test_a_setting_given_by_name_wins_over_its_variable_and_an_unknown_name_is_refused(monkeypatch):
    monkeypatch.setenv("CKS_MAX_QUEUED_REQUESTS", "7")
    assert Settings(max_queued_requests=5).predict.max_queued_requests == 5
    with pytest.raises(TypeError, match="max_queued_requestz"):
        Settings(max_queued_requestz=5)
