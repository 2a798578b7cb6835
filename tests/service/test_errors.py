"""What a client is told about unexpected exceptions: no class names, no library text;
a full disk is a 507, a body nested too deeply a 400."""

from __future__ import annotations

import errno
import sqlite3
from pathlib import Path

import pytest

from service import worker
from service.errors import internal_error
from service.requests import MapRequest
from service.session import MapSession


def _real_sqlite_full(tmp_path: Path) -> sqlite3.Error:
    """The error SQLite raises when its file cannot grow (a page cap stands in for a full
    disk: the same SQLITE_FULL code)."""
    db = sqlite3.connect(tmp_path / "full.sqlite")
    db.execute("CREATE TABLE t (x BLOB)")
    db.execute("PRAGMA max_page_count = 4")
    try:
        db.execute("INSERT INTO t VALUES (zeroblob(100000))")
    except sqlite3.Error as exc:
        return exc
    finally:
        db.close()
    raise AssertionError("SQLite accepted a row beyond its page cap")


def test_disk_full_is_507(tmp_path: Path) -> None:
    for exc in (_real_sqlite_full(tmp_path), OSError(errno.ENOSPC, "No space left on device")):
        error = internal_error(exc)
        assert error.status == 507 and error.slug == "insufficient-storage"
        assert "disk" in error.detail and str(exc) not in error.detail


def test_postgresql_disk_full_is_507() -> None:
    errors = pytest.importorskip("psycopg.errors")
    error = internal_error(errors.DiskFull("could not extend file: No space left on device"))
    assert error.status == 507 and error.slug == "insufficient-storage"
    other = internal_error(errors.UndefinedTable('relation "frames" does not exist'))
    assert other.status == 500 and "frames" not in other.detail


def test_other_errors_are_a_bare_500() -> None:
    for exc in (
        RuntimeError("Indeterminant linear system detected while working near variable x3"),
        sqlite3.OperationalError("no such table: frames"),
        KeyError("/data/maps/abc.sqlite"),
    ):
        error = internal_error(exc)
        assert error.status == 500
        for leak in (type(exc).__name__, "x3", "frames", "/data"):
            assert leak not in error.detail


def test_worker_answers_with_the_same_classification(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    full = _real_sqlite_full(tmp_path)

    class DiskFull(MapRequest[None]):
        def answer(self, session: MapSession) -> None:
            raise full

    class Deep(MapRequest[None]):
        def answer(self, session: MapSession) -> None:
            raise RecursionError("maximum recursion depth exceeded while decoding a JSON array")

    monkeypatch.setattr(worker, "_session", lambda map_id: None)
    reply = worker.call("m", DiskFull())
    assert reply["ok"] is False and reply["error"]["status"] == 507
    reply = worker.call("m", Deep())
    assert reply["error"]["status"] == 400 and "nested too deeply" in reply["error"]["detail"]
