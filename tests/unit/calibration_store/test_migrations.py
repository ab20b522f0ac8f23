"""Schema migrations: applied once, idempotent on reopen, safe under concurrent opens, and
upgrading a database written before a migration existed."""

from __future__ import annotations

from datetime import UTC, datetime

import pytest

from calibration_store import CalibrationStore, JobRecord, SchemaVersionError, open_store
from calibration_store import sqlite as sqlite_backend
from calibration_store.migrations import POSTGRES_MIGRATIONS, SQLITE_MIGRATIONS
from calibration_store.sqlstore import Cursor, EncodedBlock, SqlStore
from tests.unit.calibration_store import rawdb
from tests.unit.calibration_store.factories import MODEL_A, assert_tables_identical, new_version, score_table

LATEST = SQLITE_MIGRATIONS[-1].version


def test_backends_share_schema_versions() -> None:
    assert [m.version for m in SQLITE_MIGRATIONS] == [m.version for m in POSTGRES_MIGRATIONS]
    assert [m.version for m in SQLITE_MIGRATIONS] == list(range(1, LATEST + 1))


def test_reopen_is_idempotent(store_url: str) -> None:
    with open_store(store_url) as store:
        store.create_version(new_version(), score_table(n=3))
    for _ in range(3):
        open_store(store_url).close()
    assert rawdb.schema_versions(store_url) == list(range(1, LATEST + 1))
    with open_store(store_url) as store:
        assert [v.number for v in store.list_versions(MODEL_A)] == [1]


def test_newer_schema_is_refused(store_url: str) -> None:
    open_store(store_url).close()
    rawdb.query(
        store_url,
        "INSERT INTO calib_schema_version (version, description, applied_at)"
        f" VALUES ({LATEST + 1}, 'from the future', 'now')",
    )
    with pytest.raises(SchemaVersionError, match="newer"):
        open_store(store_url)


def open_with_schema_1(url: str, monkeypatch: pytest.MonkeyPatch) -> CalibrationStore:
    """A store opened the way the code before the job table did (only migration 1), writing
    score blocks as that code did (no content-hash columns)."""
    monkeypatch.setattr(SqlStore, "_insert_block", _insert_block_schema_1)
    # newer code reads columns schema 1 lacks (strata); nothing is read back before the upgrade
    monkeypatch.setattr(SqlStore, "get_version", lambda self, model_hash, number: None)
    with monkeypatch.context() as patch:
        patch.setattr(sqlite_backend, "SQLITE_MIGRATIONS", SQLITE_MIGRATIONS[:1])
        if url.startswith("postgresql:"):
            from calibration_store import postgres

            patch.setattr(postgres, "POSTGRES_MIGRATIONS", POSTGRES_MIGRATIONS[:1])
        return open_store(url)


def _insert_block_schema_1(self: SqlStore, cur: Cursor, version_id: int, block: EncodedBlock) -> None:
    cur.execute(
        "INSERT INTO calib_score_objects (version_id, position, object_name, n_instances,"
        " keypoint_ids, instance_refs) VALUES (?, ?, ?, ?, ?, ?)",
        (
            version_id,
            block.position,
            block.object_name,
            block.n_instances,
            block.keypoint_ids,
            block.instance_refs,
        ),
    )
    for function, rows, cols, data in block.arrays:
        cur.execute(
            "INSERT INTO calib_score_arrays (version_id, object_name, function, n_rows,"
            " n_cols, data) VALUES (?, ?, ?, ?, ?, ?)",
            (version_id, block.object_name, function, rows, cols, data),
        )


def _tables(url: str) -> set[str]:
    if url.startswith("sqlite:"):
        sql = "SELECT name FROM sqlite_master WHERE type = 'table'"
    else:
        sql = "SELECT tablename FROM pg_tables WHERE schemaname = current_schema()"
    return {row[0] for row in rawdb.query(url, sql)}


def test_database_from_before_jobs_is_upgraded(store_url: str, monkeypatch: pytest.MonkeyPatch) -> None:
    with open_with_schema_1(store_url, monkeypatch) as old:
        table = score_table(n=3, extras=False)
        old.create_version(new_version(), table)
        old.activate(MODEL_A, 1, who="alice")
    monkeypatch.undo()
    assert rawdb.schema_versions(store_url) == [1]
    assert "calib_jobs" not in _tables(store_url)

    with open_store(store_url) as store:
        assert rawdb.schema_versions(store_url) == list(range(1, LATEST + 1))
        assert "calib_jobs" in _tables(store_url)
        assert [v.number for v in store.list_versions(MODEL_A)] == [1]
        assert store.active_version(MODEL_A).version == 1
        assert_tables_identical(store.load_scores(MODEL_A, 1), table)
        now = datetime.now(UTC)
        store.create_job(JobRecord(id="j", kind="k", owner="o", created_at=now, heartbeat_at=now))
        assert store.update_job("j", state="running").state == "running"
        assert store.update_job("j", state="interrupted").state == "interrupted"
        assert not store.load_scores(MODEL_A, 1).objects[0].has_hashes  # written before hashes existed
