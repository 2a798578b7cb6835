"""The store backends every store-level test runs against: SQLite and PostgreSQL."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from service.store import MapPlace, Store, open_store
from tests.support.clusters import PrivatePostgres

PlaceFactory = Callable[[str], Path | MapPlace]
"""A map's place by name: a SQLite file path, or a map id in the PostgreSQL store."""


@pytest.fixture(params=["sqlite", "postgresql"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Store]:
    """An empty store: SQLite in a temporary directory, or a fresh PostgreSQL database."""
    if request.param == "sqlite":
        url = str(tmp_path / "store")
    else:
        server: PrivatePostgres = request.getfixturevalue("postgres")
        url = server.new_database()
    opened = open_store(url, data_dir=tmp_path / "unused", synchronous="NORMAL")
    yield opened
    opened.close()


@pytest.fixture
def place(store: Store, tmp_path: Path) -> PlaceFactory:
    """Map places in `store`; for SQLite a plain file path (as the tests always used)."""

    def make(name: str) -> Path | MapPlace:
        if store.description.startswith("SQLite"):
            return tmp_path / f"{name}.sqlite"
        return store.place(name)

    return make
