"""PostgreSQL backend (psycopg 3 + psycopg_pool), for many service replicas.

Version numbers come from an upsert on the model's row in calib_models, which holds
that row locked until commit: concurrent writers of one model queue there and get
consecutive numbers; a rolled-back or killed writer releases the row and its number.
Migrations run under a transaction-scoped advisory lock.

A database that is away fails an operation with StoreUnavailable after ``timeout_s``
(waiting for a pooled connection); reconnection attempts give up after the same time, so
the next operation after the database returns connects at once instead of waiting for the
pool's exponential backoff (up to minutes after a long outage).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from datetime import UTC, datetime
from typing import Any

try:
    import psycopg
    from psycopg_pool import ConnectionPool, PoolClosed, PoolTimeout
except ImportError as exc:  # pragma: no cover - depends on the installed extras
    raise ImportError(
        "the PostgreSQL calibration store needs psycopg 3 and psycopg_pool:"
        ' pip install "conformal-keypoint-service[postgres]"'
    ) from exc

from .errors import StoreError, StoreFull, StoreUnavailable
from .migrations import POSTGRES_MIGRATIONS, apply_migrations
from .sqlstore import Cursor, SqlStore

#: pg_advisory_xact_lock key serializing schema migrations ("calibsto" in ASCII)
MIGRATION_LOCK_KEY = 0x63616C6962737430


class _QmarkCursor:
    """Adapts the shared '?' placeholder queries to psycopg's '%s'."""

    def __init__(self, cursor: psycopg.Cursor[Any]) -> None:
        self._cursor = cursor

    def execute(self, sql: str, params: Sequence[Any] | None = None) -> Any:
        if params is None:
            return self._cursor.execute(sql)
        return self._cursor.execute(sql.replace("?", "%s"), params)

    def fetchone(self) -> Any:
        return self._cursor.fetchone()

    def fetchall(self) -> list[Any]:
        return self._cursor.fetchall()


class PostgresStore(SqlStore):
    """Calibration store in a PostgreSQL database given by a libpq URL."""

    lock_clause = " FOR UPDATE"

    def __init__(
        self,
        url: str,
        *,
        min_connections: int = 1,
        max_connections: int = 10,
        connect_timeout_s: float = 10.0,
        timeout_s: float = 10.0,
    ) -> None:
        """connect_timeout_s: how long opening waits for the database (start-up); timeout_s: how
        long one operation waits for a connection before StoreUnavailable."""
        self._timeout_s = timeout_s
        self._pool = ConnectionPool(
            url,
            min_size=min_connections,
            max_size=max_connections,
            # libpq counts whole seconds and treats less than 2 as 2
            kwargs={"autocommit": True, "connect_timeout": max(2, math.ceil(timeout_s))},
            check=ConnectionPool.check_connection,
            reconnect_timeout=timeout_s,
            open=False,
            name="calibration_store",
        )
        try:
            self._pool.open(wait=True, timeout=connect_timeout_s)
            self._migrate()
        except PoolTimeout as exc:
            self._pool.close()
            raise StoreUnavailable(f"cannot connect to PostgreSQL: {exc}") from exc
        except BaseException:
            self._pool.close()
            raise

    def _migrate(self) -> None:
        with self._transaction(write=True) as cur:
            cur.execute("SELECT pg_advisory_xact_lock(?)", (MIGRATION_LOCK_KEY,))
            apply_migrations(cur, POSTGRES_MIGRATIONS)

    @contextmanager
    def _transaction(self, write: bool) -> Iterator[Cursor]:
        try:
            with (
                self._pool.connection(timeout=self._timeout_s) as conn,
                conn.transaction(),
                conn.cursor(binary=True) as cursor,
            ):
                yield _QmarkCursor(cursor)
        except PoolClosed as exc:
            raise StoreError("the calibration store is closed") from exc
        except PoolTimeout as exc:
            raise StoreUnavailable(f"no PostgreSQL connection available: {exc}") from exc
        except psycopg.errors.DiskFull as exc:
            raise StoreFull(f"PostgreSQL error: {exc}") from exc
        except psycopg.OperationalError as exc:
            raise StoreUnavailable(f"PostgreSQL error: {exc}") from exc

    def _time_to_db(self, value: datetime) -> datetime:
        return value.astimezone(UTC)

    def _time_from_db(self, value: Any) -> datetime:
        return value.astimezone(UTC)

    def close(self) -> None:
        self._pool.close()

    def __repr__(self) -> str:
        return f"PostgresStore(pool={self._pool.name!r})"
