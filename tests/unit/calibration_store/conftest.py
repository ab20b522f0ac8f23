"""Every behavioural test runs against both backends: SQLite file and real PostgreSQL."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from calibration_store import CalibrationStore, open_store


@pytest.fixture(params=["sqlite", "postgres"])
def store_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """URL of an empty store of each backend."""
    if request.param == "sqlite":
        return f"sqlite://{tmp_path}/data/calibration.db"
    return request.getfixturevalue("postgres_url")


@pytest.fixture
def store(store_url: str) -> Iterator[CalibrationStore]:
    opened = open_store(store_url)
    yield opened
    opened.close()
