"""The embedded SQLite store (service.store): a catalogue, and one database file per map.

Layout under the data directory::

    catalog.sqlite          maps(id, name, mode, config, created),
                            keys(id, map_id, scope, hash, created): API keys, hashed
    maps/<id>.sqlite        frames (the durable log), images, image observations,
                            snapshots, front-end states, removal log, archive, final
                            trajectory rows, events, meta

Every database runs in WAL mode; ``synchronous`` is NORMAL (survives a killed
process: a commit is in the OS before it returns) or FULL (also survives power
loss, one fsync per commit). The catalogue is written by the API process, a map's
file only by the worker process that owns the map; anyone may read. What the tables
hold and when they are written: service.store; the statements both stores run are
written once in service.store_sql. ``removals`` is the older, one row per landmark,
form of the removal log; a file that still has rows in it has them moved into
``removal_log`` when it is opened.
"""

from __future__ import annotations

import shutil
import sqlite3
from collections.abc import Iterator, Sequence
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import Any

from service.store_sql import Args, Catalog, MapReads, MapStore

_CATALOG_SCHEMA = """
CREATE TABLE IF NOT EXISTS maps (
    id TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    mode TEXT NOT NULL,
    config TEXT NOT NULL,
    created REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS keys (
    id TEXT PRIMARY KEY,
    map_id TEXT NOT NULL,
    scope TEXT NOT NULL,
    hash TEXT NOT NULL UNIQUE,
    created REAL NOT NULL
);
"""

_MAP_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS frames (
    id INTEGER PRIMARY KEY,
    robot TEXT NOT NULL,
    seq INTEGER NOT NULL,
    body TEXT NOT NULL,
    result TEXT,
    attempts INTEGER NOT NULL DEFAULT 0,
    received REAL NOT NULL,
    UNIQUE (robot, seq)
);
CREATE TABLE IF NOT EXISTS images (
    frame_id INTEGER PRIMARY KEY,
    data BLOB NOT NULL
);
CREATE TABLE IF NOT EXISTS image_observations (
    frame_id INTEGER PRIMARY KEY,
    observations TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS frontend_states (
    snapshot_id INTEGER PRIMARY KEY,
    state BLOB NOT NULL
);
CREATE TABLE IF NOT EXISTS snapshots (
    id INTEGER PRIMARY KEY,
    upto INTEGER NOT NULL,
    created REAL NOT NULL,
    state BLOB NOT NULL
);
CREATE TABLE IF NOT EXISTS removals (
    landmark_id INTEGER PRIMARY KEY,
    frame INTEGER NOT NULL,
    record TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS removal_log (
    frame INTEGER NOT NULL,
    landmark_id INTEGER NOT NULL,
    record TEXT NOT NULL,
    PRIMARY KEY (frame, landmark_id)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS archive (
    landmark_id INTEGER PRIMARY KEY,
    frame INTEGER NOT NULL,
    record TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS poses (
    robot TEXT NOT NULL,
    seq INTEGER NOT NULL,
    stamp REAL NOT NULL,
    x REAL NOT NULL,
    y REAL NOT NULL,
    theta REAL NOT NULL,
    PRIMARY KEY (robot, seq)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    kind TEXT NOT NULL,
    data TEXT NOT NULL,
    created REAL NOT NULL
);
"""


def connect(path: Path, *, synchronous: str, readonly: bool = False) -> sqlite3.Connection:
    """A connection in WAL mode with the given synchronous level (autocommit mode)."""
    if readonly:
        conn = sqlite3.connect(
            f"file:{path}?mode=ro", uri=True, isolation_level=None, check_same_thread=False
        )
    else:
        path.parent.mkdir(parents=True, exist_ok=True)
        conn = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
        conn.execute("PRAGMA journal_mode=WAL")
    conn.execute(f"PRAGMA synchronous={'FULL' if synchronous == 'FULL' else 'NORMAL'}")
    conn.execute("PRAGMA busy_timeout=10000")
    return conn


@contextmanager
def transaction(conn: sqlite3.Connection) -> Iterator[sqlite3.Connection]:
    """BEGIN IMMEDIATE ... COMMIT, rolled back on any exception."""
    conn.execute("BEGIN IMMEDIATE")
    try:
        yield conn
    except BaseException:
        conn.execute("ROLLBACK")
        raise
    conn.execute("COMMIT")


def map_db_path(data_dir: Path, map_id: str) -> Path:
    return data_dir / "maps" / f"{map_id}.sqlite"


class _Connection:
    """Reads and single committed writes on a database file's connection `_conn`."""

    _conn: sqlite3.Connection

    def close(self) -> None:
        self._conn.close()

    def _rows(self, sql: str, args: Args) -> list[Any]:
        return self._conn.execute(sql, args).fetchall()

    def _write(self, sql: str, args: Args) -> None:
        with transaction(self._conn):
            self._conn.execute(sql, args)


# --------------------------------------------------------------------------- catalogue


class SqliteCatalog(_Connection, Catalog):
    """The list of maps and their API keys (API process): ``catalog.sqlite`` in the data
    directory."""

    def __init__(self, data_dir: Path, *, synchronous: str) -> None:
        data_dir.mkdir(parents=True, exist_ok=True)
        self._conn = connect(data_dir / "catalog.sqlite", synchronous=synchronous)
        self._conn.executescript(_CATALOG_SCHEMA)

    def remove(self, map_id: str) -> None:
        """Delete a map's record and its keys."""
        with transaction(self._conn):
            self._conn.execute("DELETE FROM maps WHERE id = ?", (map_id,))
            self._conn.execute("DELETE FROM keys WHERE map_id = ?", (map_id,))


# --------------------------------------------------------------------------- one map


class SqliteMapStore(_Connection, MapStore):
    """One map's database file (owned by its worker process)."""

    SCOPED = False
    FRAME_STATS = (
        "SELECT id, robot, seq, json_extract(result, '$.landmarks.live'), "
        "json_extract(result, '$.landmarks.added'), "
        "json_extract(result, '$.landmarks.marginalised'), "
        "json_extract(result, '$.timing_ms.total'), json_extract(result, '$.covariance') "
        "FROM frames WHERE result IS NOT NULL ORDER BY id"
    )
    REMOVED_LABELS = "SELECT DISTINCT landmark_id, json_extract(record, '$.label') FROM removal_log"

    def __init__(self, path: Path, *, synchronous: str) -> None:
        self.path = path
        self._conn = connect(path, synchronous=synchronous)
        self._conn.executescript(_MAP_SCHEMA)
        if self._conn.execute("SELECT 1 FROM removals LIMIT 1").fetchone() is not None:
            with transaction(self._conn):  # a file from before the removal log
                self._conn.execute(
                    "INSERT OR IGNORE INTO removal_log (frame, landmark_id, record) "
                    "SELECT frame, landmark_id, record FROM removals"
                )
                self._conn.execute("DELETE FROM removals")

    def _insert(self, sql: str, args: Args) -> int:
        row_id = self._conn.execute(sql, args).lastrowid
        assert row_id is not None
        return row_id

    def _many(self, sql: str, rows: Sequence[Args]) -> None:
        self._conn.executemany(sql, rows)

    def _transaction(self) -> AbstractContextManager[Any]:
        return transaction(self._conn)

    def checkpoint(self) -> None:
        """Fold the WAL into the database file (so its size on disk says what it holds)."""
        self._conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")


def remove_map_files(path: Path) -> None:
    """Delete a map's database and its WAL/SHM companions."""
    for suffix in ("", "-wal", "-shm"):
        p = Path(str(path) + suffix)
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()


class SqliteMap:
    """A map's database file (service.store.MapPlace)."""

    def __init__(self, path: Path, *, synchronous: str, map_id: str | None = None) -> None:
        self.path = path
        self.map_id = map_id or path.stem
        self._synchronous = synchronous

    def __str__(self) -> str:
        return str(self.path)

    def exists(self) -> bool:
        return self.path.exists()

    def open(self) -> SqliteMapStore:
        return SqliteMapStore(self.path, synchronous=self._synchronous)

    def remove(self) -> None:
        remove_map_files(self.path)


class SqliteStore(MapReads):
    """The embedded store under a data directory (service.store.Store)."""

    SCOPED = False

    def __init__(self, data_dir: Path, *, synchronous: str) -> None:
        self.data_dir = data_dir
        self.description = f"SQLite in {data_dir}"
        self._synchronous = synchronous

    def catalog(self) -> SqliteCatalog:
        return SqliteCatalog(self.data_dir, synchronous=self._synchronous)

    def place(self, map_id: str) -> SqliteMap:
        return SqliteMap(
            map_db_path(self.data_dir, map_id), synchronous=self._synchronous, map_id=map_id
        )

    def _read(self, map_id: str, sql: str, args: Args) -> list[Any]:
        path = map_db_path(self.data_dir, map_id)
        if not path.exists():
            return []
        conn = connect(path, synchronous="NORMAL", readonly=True)
        try:
            return conn.execute(sql, args).fetchall()
        finally:
            conn.close()

    def close(self) -> None:
        """Nothing to close: each call opens its own connection."""
