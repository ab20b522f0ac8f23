"""Choose and open a backend from one URL setting."""

from __future__ import annotations

from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

from .base import CalibrationStore


def sqlite_path(url: str) -> Path:
    """The file path of a sqlite URL.

    sqlite:///abs/path.db and sqlite:////abs/path.db -> /abs/path.db (absolute);
    sqlite:relative/path.db -> relative to the current directory.
    """
    rest = url[len("sqlite:") :]
    if rest.startswith("//"):
        rest = rest[2:]
        if not rest.startswith("/"):
            raise ValueError(
                f"sqlite URL {url!r} names a host; use sqlite:///absolute/path.db or sqlite:relative/path.db"
            )
        rest = "/" + rest.lstrip("/")
    if not rest or "?" in rest or "#" in rest or rest == ":memory:":
        raise ValueError(
            f"sqlite URL {url!r} must name a database file (no query, no :memory:),"
            " e.g. sqlite:///var/lib/keypoints/calibration.db"
        )
    return Path(unquote(rest))


def open_store(url: str, **options: Any) -> CalibrationStore:
    """Open (creating and migrating if needed) the store a URL names.

    url: sqlite:///abs/path.db, sqlite:relative/path.db, or postgresql://user@host/db
    (also postgres://). options go to the backend: SQLite busy_timeout_s; PostgreSQL
    min_connections, max_connections, connect_timeout_s.
    """
    if not isinstance(url, str):
        raise TypeError("the store URL must be a string")
    scheme = url.split(":", 1)[0].lower() if ":" in url else ""
    if scheme == "sqlite":
        from .sqlite import SQLiteStore

        return SQLiteStore(sqlite_path(url), **options)
    if scheme in ("postgresql", "postgres"):
        from .postgres import PostgresStore

        return PostgresStore(url, **options)
    raise ValueError(
        f"unsupported calibration store URL {url!r}: use sqlite:///path/to/file.db"
        " or postgresql://user@host:port/database"
    )


def store_location(url: str) -> tuple[str, str]:
    """The backend kind and where it is, without secrets: ("sqlite", "/abs/path.db") or
    ("postgresql", "postgresql://user@host:5432/db") with any password and query removed."""
    scheme = url.split(":", 1)[0].lower() if ":" in url else ""
    if scheme == "sqlite":
        return "sqlite", str(sqlite_path(url).resolve())
    parts = urlsplit(url)
    host = parts.hostname or ""
    if parts.port:
        host = f"{host}:{parts.port}"
    user = f"{parts.username}@" if parts.username else ""
    return "postgresql", f"postgresql://{user}{host}{parts.path}"
