"""Database trouble surfaces as StoreUnavailable (HTTP 503), never as a partial write."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from calibration_store import StoreUnavailable, open_store
from tests.postgres_cluster import free_port
from tests.unit.calibration_store.factories import MODEL_A, new_version, score_table


def test_sqlite_write_lock_held_too_long(tmp_path: Path) -> None:
    path = tmp_path / "c.db"
    with open_store(f"sqlite://{path}", busy_timeout_s=0.2) as store:
        blocker = sqlite3.connect(path, isolation_level=None)
        blocker.execute("BEGIN IMMEDIATE")
        try:
            with pytest.raises(StoreUnavailable, match="locked"):
                store.create_version(new_version(), score_table(n=2))
            assert store.list_versions(MODEL_A) == []  # readers are not blocked (WAL)
        finally:
            blocker.execute("ROLLBACK")
            blocker.close()
        assert store.create_version(new_version(), score_table(n=2)).number == 1


def test_sqlite_a_connection_that_cannot_be_opened_is_unavailable(tmp_path: Path) -> None:
    """A new connection fails as a transaction would (another process's WAL locks, a file gone):
    StoreUnavailable, never sqlite3's own error (which answered 500 under load)."""
    path = tmp_path / "c.db"
    with open_store(f"sqlite://{path}") as store:
        store.list_versions(MODEL_A)
        path.unlink()
        (tmp_path / "c.db-wal").unlink(missing_ok=True)
        path.mkdir()  # a folder where the database was: sqlite3 cannot open it
        with (
            store._pool.connection(),  # the idle connection: the next one must be opened
            pytest.raises(StoreUnavailable, match="could not open a connection"),
        ):
            store.list_versions(MODEL_A)


def test_postgres_unreachable() -> None:
    url = f"postgresql://postgres@127.0.0.1:{free_port()}/nowhere"
    with pytest.raises(StoreUnavailable, match="cannot connect"):
        open_store(url, connect_timeout_s=1.0)
