"""Paths in the settings are resolved once, against the directory the service starts in."""

from __future__ import annotations

from pathlib import Path

import pytest

from service.infra.operators import OperatorsError, load_operators
from service.infra.settings import Settings


def test_relative_paths_are_resolved_against_the_starting_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("CKS_DATA_DIR", "var")
    monkeypatch.delenv("CKS_STORE_URL", raising=False)
    settings = Settings()
    assert settings.storage.data_dir == tmp_path / "var"
    assert settings.storage.resolved_url == f"sqlite:///{tmp_path / 'var' / 'calibrations.db'}"
    monkeypatch.setenv("CKS_STORE_URL", "sqlite:stores/cal.db")
    assert Settings().storage.resolved_url == f"sqlite:///{tmp_path / 'stores' / 'cal.db'}"


def test_operators_come_from_the_token_and_the_tokens_file(tmp_path: Path) -> None:
    tokens = tmp_path / "tokens"
    tokens.write_text("# operators\n\nalice: alice-token-0123456789\nbob:bob-token-9876543210\n")
    assert load_operators("single-admin-token", tokens) == {
        "single-admin-token": "admin",
        "alice-token-0123456789": "alice",
        "bob-token-9876543210": "bob",
    }
    assert load_operators(None, None) == {}


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("alice\n", "line 1: write 'name:token'"),
        ("al ice:alice-token-0123456789\n", "line 1: write 'name:token'"),
        ("alice:short\n", "at least 16 characters"),
        ("alice:alice-token-0123456789\nbob:alice-token-0123456789\n", "line 2: this token is already"),
        ("alice:alice-token-0123456789\nalice:other-token-0123456789\n", "the name 'alice' is used twice"),
        ("# nobody\n", "names no operator"),
    ],
)
def test_a_bad_tokens_file_is_refused_naming_the_line(tmp_path: Path, text: str, message: str) -> None:
    tokens = tmp_path / "tokens"
    tokens.write_text(text)
    with pytest.raises(OperatorsError, match=message):
        load_operators(None, tokens)


@pytest.mark.parametrize("token", ["change-me", "fifteen-chars15", "sixteen chars 16"])
def test_one_rule_for_a_token_wherever_it_is_configured(tmp_path: Path, token: str) -> None:
    tokens = tmp_path / "tokens"
    tokens.write_text(f"alice:{token}\n")
    with pytest.raises(OperatorsError, match="CKS_ADMIN_TOKEN: the token must be at least 16 characters"):
        load_operators(token, None)
    with pytest.raises(OperatorsError, match="the token of 'alice' must be at least 16 characters"):
        load_operators(None, tokens)
    assert load_operators("sixteen-chars-16", None) == {"sixteen-chars-16": "admin"}


def test_a_missing_tokens_file_is_refused(tmp_path: Path) -> None:
    with pytest.raises(OperatorsError, match="cannot read"):
        load_operators(None, tmp_path / "absent")
