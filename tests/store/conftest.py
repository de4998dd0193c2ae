"""Store fixtures: every store test runs on SQLite and on a real PostgreSQL server."""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from pathlib import Path

import pytest

from cellctl.store import Store
from tests.store.pgcluster import PostgresCluster

_cells = itertools.count()


@pytest.fixture(scope="session")
def postgres() -> Iterator[PostgresCluster]:
    """One throwaway PostgreSQL server for the session, always stopped at the end."""
    cluster = PostgresCluster()
    try:
        cluster.start()
        yield cluster
    finally:
        cluster.stop()


@pytest.fixture(scope="session")
def postgres_url(postgres: PostgresCluster) -> str:
    """One database shared by the store tests, as a plant would share one among its cells."""
    return postgres.create_database("cellctl_store_tests")


@pytest.fixture(params=["sqlite", "postgresql"])
def store_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """A store URL on each backend (PostgreSQL only started when a test needs it)."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'store.db'}"
    return str(request.getfixturevalue("postgres_url"))


@pytest.fixture
def cell_id() -> str:
    """A cell id unique to the test: tests sharing the PostgreSQL database never see each other."""
    return f"cell-{next(_cells)}"


@pytest.fixture
def store(store_url: str, cell_id: str) -> Iterator[Store]:
    s = Store(store_url, cell_id)
    try:
        yield s
    finally:
        s.close()
