"""Schema migrations: applied once, idempotent on reopen, safe under concurrent opens."""

from __future__ import annotations

import pytest

from calibration_store import SchemaVersionError, open_store
from calibration_store.migrations import POSTGRES_MIGRATIONS, SQLITE_MIGRATIONS
from tests.store import rawdb
from tests.store.factories import MODEL_A, new_version, score_table
from tests.store.processes import run_together
from tests.store.workers import open_concurrently

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


def test_concurrent_first_opens_migrate_once(store_url: str) -> None:
    seen = run_together(open_concurrently, [(store_url,)] * 4)
    assert seen == [list(range(1, LATEST + 1))] * 4


def test_newer_schema_is_refused(store_url: str) -> None:
    open_store(store_url).close()
    rawdb.query(
        store_url,
        "INSERT INTO calib_schema_version (version, description, applied_at)"
        f" VALUES ({LATEST + 1}, 'from the future', 'now')",
    )
    with pytest.raises(SchemaVersionError, match="newer"):
        open_store(store_url)
