"""PostgreSQL backend (psycopg 3 + psycopg_pool), for many service replicas.

Version numbers come from an upsert on the model's row in calib_models, which holds
that row locked until commit: concurrent writers of one model queue there and get
consecutive numbers; a rolled-back or killed writer releases the row and its number.
Migrations run under a transaction-scoped advisory lock.

A database that is away fails an operation with StoreUnavailable after ``timeout_s``
(waiting for a pooled connection); reconnection attempts give up after the same time, so
the next operation after the database returns connects at once instead of waiting for the
pool's exponential backoff (up to minutes after a long outage). Every call is bounded by the
same time: the server cancels a statement or a lock wait past it (``statement_timeout``,
``lock_timeout``), and a watchdog cuts the connection of a database that has not answered a
round trip within it (a frozen server, SIGSTOP or a paused VM, neither answers nor closes its
sockets, and cannot run its own timeouts).
"""

from __future__ import annotations

import math
import os
import socket
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
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


class _Watchdog:
    """Cuts ``conn``'s socket once the database has not answered within ``seconds`` of the
    last ``renew`` (each round trip renews it), so the call waiting on it fails at once."""

    def __init__(self, conn: psycopg.Connection[Any], seconds: float) -> None:
        self._conn, self._seconds = conn, seconds
        self._deadline = time.monotonic() + seconds
        self._done = threading.Event()
        self.fired = False
        threading.Thread(target=self._watch, name="store-watchdog", daemon=True).start()

    def renew(self) -> None:
        self._deadline = time.monotonic() + self._seconds

    def stop(self) -> None:
        self._done.set()

    def _watch(self) -> None:
        while not self._done.wait(max(0.0, self._deadline - time.monotonic())):
            if time.monotonic() >= self._deadline:
                self.fired = True
                # (closed meanwhile: nothing to cut) the original descriptor sees the end too
                with suppress(Exception), socket.socket(fileno=os.dup(self._conn.fileno())) as sock:
                    sock.shutdown(socket.SHUT_RDWR)
                return


@contextmanager
def _watched(conn: psycopg.Connection[Any], seconds: float) -> Iterator[_Watchdog]:
    watchdog = _Watchdog(conn, seconds)
    try:
        yield watchdog
    except psycopg.OperationalError as exc:
        if watchdog.fired:
            raise StoreUnavailable(f"PostgreSQL did not answer within {seconds:g} s") from exc
        raise
    finally:
        watchdog.stop()


class _QmarkCursor:
    """Adapts the shared '?' placeholder queries to psycopg's '%s'; each renews the watchdog."""

    def __init__(self, cursor: psycopg.Cursor[Any], watchdog: _Watchdog) -> None:
        self._cursor, self._watchdog = cursor, watchdog

    def execute(self, sql: str, params: Sequence[Any] | None = None) -> Any:
        self._watchdog.renew()
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
        long one operation waits for a connection, and one statement or round trip for the
        database, before StoreUnavailable."""
        self._timeout_s, self._connect_timeout_s = timeout_s, connect_timeout_s
        milliseconds = math.ceil(1000 * timeout_s)
        self._pool = ConnectionPool(
            url,
            min_size=min_connections,
            max_size=max_connections,
            kwargs={
                "autocommit": True,
                # libpq counts whole seconds and treats less than 2 as 2
                "connect_timeout": max(2, math.ceil(timeout_s)),
                "options": f"-c statement_timeout={milliseconds} -c lock_timeout={milliseconds}",
            },
            check=self._check,
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

    def _check(self, conn: psycopg.Connection[Any]) -> None:
        """The pool's check of a connection it hands out, bounded like every call."""
        with _watched(conn, self._timeout_s):
            ConnectionPool.check_connection(conn)

    def _migrate(self) -> None:
        """Under a lock that replicas starting together queue for: their wait is start-up's."""
        with self._transaction(write=True, timeout_s=self._connect_timeout_s) as cur:
            wait = f"{math.ceil(1000 * self._connect_timeout_s)}ms"
            cur.execute(f"SET LOCAL statement_timeout = '{wait}'")
            cur.execute(f"SET LOCAL lock_timeout = '{wait}'")
            cur.execute("SELECT pg_advisory_xact_lock(?)", (MIGRATION_LOCK_KEY,))
            apply_migrations(cur, POSTGRES_MIGRATIONS)

    @contextmanager
    def _transaction(self, write: bool, timeout_s: float | None = None) -> Iterator[Cursor]:
        try:
            with (
                self._pool.connection(timeout=self._timeout_s) as conn,
                _watched(conn, timeout_s or self._timeout_s) as watchdog,
                conn.transaction(),
                conn.cursor(binary=True) as cursor,
            ):
                yield _QmarkCursor(cursor, watchdog)
                watchdog.renew()  # the commit's round trip
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
