"""SQLite backend: one database file, WAL mode, a small pool of connections.

Writers serialize on BEGIN IMMEDIATE (waiting up to busy_timeout); readers use WAL
snapshots and never block writers. synchronous=FULL: a committed version survives
power loss, an uncommitted one is discarded by WAL recovery.
"""

from __future__ import annotations

import sqlite3
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from .errors import StoreError, StoreFull, StoreUnavailable
from .migrations import SQLITE_MIGRATIONS, apply_migrations
from .sqlstore import Cursor, SqlStore


class _ConnectionPool:
    """Connections handed to one thread at a time; idle ones are kept for reuse."""

    def __init__(self, path: Path, busy_timeout_s: float, max_idle: int = 8) -> None:
        self._path = path
        self._busy_timeout_s = busy_timeout_s
        self._max_idle = max_idle
        self._idle: list[sqlite3.Connection] = []
        self._lock = threading.Lock()
        self._closed = False

    def _connect(self) -> sqlite3.Connection:
        conn = sqlite3.connect(
            self._path,
            timeout=self._busy_timeout_s,
            isolation_level=None,
            check_same_thread=False,
        )
        conn.execute(f"PRAGMA busy_timeout = {int(self._busy_timeout_s * 1000)}")
        conn.execute("PRAGMA foreign_keys = ON")
        conn.execute("PRAGMA synchronous = FULL")
        return conn

    @contextmanager
    def connection(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            if self._closed:
                raise StoreError("the calibration store is closed")
            conn = self._idle.pop() if self._idle else None
        if conn is None:
            try:
                conn = self._connect()
            except sqlite3.OperationalError as exc:  # a lock held by another process: as in a transaction
                raise _unavailable(f"SQLite could not open a connection: {exc}", exc) from exc
        try:
            yield conn
        finally:
            self._release(conn)

    def _release(self, conn: sqlite3.Connection) -> None:
        with self._lock:
            if not self._closed and len(self._idle) < self._max_idle and not conn.in_transaction:
                self._idle.append(conn)
                return
        conn.close()

    def close(self) -> None:
        with self._lock:
            self._closed = True
            idle, self._idle = self._idle, []
        for conn in idle:
            conn.close()


class SQLiteStore(SqlStore):
    """Calibration store in one SQLite file (parent directories are created)."""

    def __init__(self, path: str | Path, *, busy_timeout_s: float = 30.0) -> None:
        self.path = Path(path).resolve()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._pool = _ConnectionPool(self.path, busy_timeout_s)
        try:
            self._migrate()
        except BaseException:
            self._pool.close()
            raise

    def _migrate(self) -> None:
        with self._pool.connection() as conn:
            _retry_locked(lambda: conn.execute("PRAGMA journal_mode = WAL"))
        with self._transaction(write=True) as cur:
            apply_migrations(cur, SQLITE_MIGRATIONS)

    @contextmanager
    def _transaction(self, write: bool) -> Iterator[Cursor]:
        with self._pool.connection() as conn:
            cur = conn.cursor()
            try:
                _execute(cur, "BEGIN IMMEDIATE" if write else "BEGIN")
                yield cur
                _execute(cur, "COMMIT")
            except sqlite3.OperationalError as exc:  # locked, disk full, I/O error
                raise _unavailable(f"SQLite error: {exc}", exc) from exc
            finally:
                if conn.in_transaction:
                    conn.execute("ROLLBACK")
                cur.close()

    def _time_to_db(self, value: datetime) -> str:
        return value.astimezone(UTC).isoformat()

    def _time_from_db(self, value: Any) -> datetime:
        return datetime.fromisoformat(value).astimezone(UTC)

    def close(self) -> None:
        self._pool.close()

    def __repr__(self) -> str:
        return f"SQLiteStore({str(self.path)!r})"


def _execute(cur: sqlite3.Cursor, statement: str) -> None:
    try:
        cur.execute(statement)
    except sqlite3.OperationalError as exc:
        raise _unavailable(f"SQLite {statement} failed: {exc}", exc) from exc


def _unavailable(message: str, error: sqlite3.OperationalError) -> StoreUnavailable:
    full = error.sqlite_errorcode == sqlite3.SQLITE_FULL
    return StoreFull(message) if full else StoreUnavailable(message)


def _retry_locked(action: Any, attempts: int = 50) -> Any:
    """Run `action`, retrying while another process holds the file lock briefly."""
    for attempt in range(attempts):
        try:
            return action()
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) or attempt == attempts - 1:
                raise StoreUnavailable(f"SQLite stayed locked: {exc}") from exc
            time.sleep(0.1)
    return None
