"""Direct database access for assertions the public interface does not expose."""

from __future__ import annotations

import sqlite3
from typing import Any

from calibration_store import sqlite_path


def query(url: str, sql: str) -> list[tuple[Any, ...]]:
    """Run one statement outside the store (autocommit) and return its rows."""
    if url.startswith("sqlite:"):
        conn = sqlite3.connect(sqlite_path(url), isolation_level=None)
        try:
            return [tuple(row) for row in conn.execute(sql).fetchall()]
        finally:
            conn.close()
    import psycopg

    with psycopg.connect(url, autocommit=True) as conn:
        cur = conn.execute(sql)
        return [tuple(row) for row in cur.fetchall()] if cur.description else []


def schema_versions(url: str) -> list[int]:
    return [row[0] for row in query(url, "SELECT version FROM calib_schema_version ORDER BY 1")]
