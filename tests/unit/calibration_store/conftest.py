"""Every behavioural test runs against both backends (store_url, tests/conftest.py): SQLite file
and real PostgreSQL."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from calibration_store import CalibrationStore, open_store


@pytest.fixture
def store(store_url: str) -> Iterator[CalibrationStore]:
    opened = open_store(store_url)
    yield opened
    opened.close()
