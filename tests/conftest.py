"""Shared fixtures. PostgreSQL: a throwaway cluster per session, a fresh database per test.

Other test folders just request `postgres_url` (a postgresql:// URL of an empty
database) or `postgres_cluster` (tests.postgres_cluster.PostgresCluster).
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.postgres_cluster import PostgresCluster


@pytest.fixture(scope="session")
def postgres_cluster() -> Iterator[PostgresCluster]:
    """A PostgreSQL server started from the machine's binaries; fails loudly if absent."""
    cluster = PostgresCluster.start()
    try:
        yield cluster
    finally:
        cluster.stop()


@pytest.fixture
def postgres_url(postgres_cluster: PostgresCluster) -> Iterator[str]:
    """URL of a fresh, empty database, dropped after the test."""
    url = postgres_cluster.create_database()
    yield url
    postgres_cluster.drop_database(url.rsplit("/", 1)[1])
