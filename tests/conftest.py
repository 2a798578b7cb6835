"""Servers shared by the whole test session: a private PostgreSQL cluster."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.support.clusters import PrivatePostgres, Unavailable


@pytest.fixture(scope="session")
def postgres() -> Iterator[PrivatePostgres]:
    """A PostgreSQL server of the session's own (skips, saying why, where none can start)."""
    pytest.importorskip("psycopg", reason="psycopg not installed (pip install -e '.[postgres]')")
    server = PrivatePostgres(fsync=False)
    try:
        server.start()
    except Unavailable as exc:
        server.stop()
        pytest.skip(f"PostgreSQL cannot start here: {exc}")
    yield server
    server.stop()
