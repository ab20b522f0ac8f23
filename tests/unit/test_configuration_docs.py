"""The README documents every setting, under the name the service reads."""

from __future__ import annotations

from pathlib import Path

from service.settings import Settings

README = Path(__file__).resolve().parents[2] / "README.md"


def test_every_setting_is_in_the_readme_configuration_table():
    text = README.read_text(encoding="utf-8")
    missing = [f"CKS_{name.upper()}" for name in Settings.model_fields if f"`CKS_{name.upper()}`" not in text]
    assert not missing, f"add these settings to README.md's Configuration table: {missing}"


def test_every_setting_has_a_description():
    undocumented = [name for name, field in Settings.model_fields.items() if not field.description]
    assert not undocumented, f"give these settings a Field(description=...): {undocumented}"


def test_settings_are_read_from_prefixed_environment(monkeypatch):
    monkeypatch.setenv("CKS_MAX_INSTANCES", "7")
    monkeypatch.setenv("CKS_STORE_URL", "sqlite:////tmp/x.db")
    settings = Settings()
    assert settings.max_instances == 7
    assert settings.resolved_store_url == "sqlite:////tmp/x.db"
