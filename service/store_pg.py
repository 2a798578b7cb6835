"""The PostgreSQL store (service.store) through psycopg 3: every map in one database.

The tables are those of the SQLite store, each with a leading ``map_id`` column in
its key, plus the catalogue: ``maps`` and the maps' API keys ``keys`` (hashed). The
semantics are the same: a frame is appended (committed) before it is processed; its
result, events, removals and final trajectory rows are written in one transaction
afterwards; ``UNIQUE (map_id, robot, seq)`` backs idempotent retries. Ids (log,
snapshot, event) count from 1 per map as SQLite's row ids do (``max(id) + 1``: one
process writes a map at a time). Text columns use the "C" collation, so rows sort as
SQLite sorts them (bytewise). The SQLite store's older ``removals`` table (moved
into ``removal_log`` when a file is opened) has no counterpart here.

Every commit is durable as PostgreSQL's ``synchronous_commit`` (default on) makes it;
the SQLite ``synchronous`` setting does not apply here. Snapshots, images and the
front end's state are ``bytea``. Results stay the exact JSON text the worker made.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from contextlib import AbstractContextManager
from typing import Any
from urllib.parse import urlsplit, urlunsplit

from service.store_sql import Args, Catalog, MapReads, MapStore, pyformat

try:
    import psycopg
except ImportError:  # pragma: no cover - exercised only without the extra
    psycopg = None  # type: ignore[assignment]

CONNECTION_ERRORS: tuple[type[Exception], ...] = (
    () if psycopg is None else (psycopg.OperationalError, psycopg.InterfaceError)
)
"""What psycopg raises when the server went away (the connection must be reopened)."""

_SCHEMA_LOCK = 0x636F76736C616D  # pg_advisory_xact_lock key while creating the schema
_MAP_TABLES = (
    "map_meta",
    "frames",
    "images",
    "image_observations",
    "frontend_states",
    "snapshots",
    "removal_log",
    "archive",
    "poses",
    "events",
)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS maps (
    id TEXT COLLATE "C" PRIMARY KEY,
    name TEXT NOT NULL,
    mode TEXT NOT NULL,
    config TEXT NOT NULL,
    created DOUBLE PRECISION NOT NULL
);
CREATE TABLE IF NOT EXISTS keys (
    id TEXT COLLATE "C" PRIMARY KEY,
    map_id TEXT COLLATE "C" NOT NULL,
    scope TEXT NOT NULL,
    hash TEXT NOT NULL UNIQUE,
    created DOUBLE PRECISION NOT NULL
);
CREATE TABLE IF NOT EXISTS map_meta (
    map_id TEXT COLLATE "C" NOT NULL,
    key TEXT COLLATE "C" NOT NULL,
    value TEXT NOT NULL,
    PRIMARY KEY (map_id, key)
);
CREATE TABLE IF NOT EXISTS frames (
    map_id TEXT COLLATE "C" NOT NULL,
    id BIGINT NOT NULL,
    robot TEXT COLLATE "C" NOT NULL,
    seq BIGINT NOT NULL,
    body TEXT NOT NULL,
    result TEXT,
    attempts INTEGER NOT NULL DEFAULT 0,
    received DOUBLE PRECISION NOT NULL,
    PRIMARY KEY (map_id, id),
    UNIQUE (map_id, robot, seq)
);
CREATE TABLE IF NOT EXISTS images (
    map_id TEXT COLLATE "C" NOT NULL,
    frame_id BIGINT NOT NULL,
    data BYTEA NOT NULL,
    PRIMARY KEY (map_id, frame_id)
);
CREATE TABLE IF NOT EXISTS image_observations (
    map_id TEXT COLLATE "C" NOT NULL,
    frame_id BIGINT NOT NULL,
    observations TEXT NOT NULL,
    PRIMARY KEY (map_id, frame_id)
);
CREATE TABLE IF NOT EXISTS frontend_states (
    map_id TEXT COLLATE "C" NOT NULL,
    snapshot_id BIGINT NOT NULL,
    state BYTEA NOT NULL,
    PRIMARY KEY (map_id, snapshot_id)
);
CREATE TABLE IF NOT EXISTS snapshots (
    map_id TEXT COLLATE "C" NOT NULL,
    id BIGINT NOT NULL,
    upto BIGINT NOT NULL,
    created DOUBLE PRECISION NOT NULL,
    state BYTEA NOT NULL,
    PRIMARY KEY (map_id, id)
);
CREATE TABLE IF NOT EXISTS removal_log (
    map_id TEXT COLLATE "C" NOT NULL,
    frame BIGINT NOT NULL,
    landmark_id BIGINT NOT NULL,
    record TEXT NOT NULL,
    PRIMARY KEY (map_id, frame, landmark_id)
);
CREATE TABLE IF NOT EXISTS archive (
    map_id TEXT COLLATE "C" NOT NULL,
    landmark_id BIGINT NOT NULL,
    frame BIGINT NOT NULL,
    record TEXT NOT NULL,
    PRIMARY KEY (map_id, landmark_id)
);
CREATE TABLE IF NOT EXISTS poses (
    map_id TEXT COLLATE "C" NOT NULL,
    robot TEXT COLLATE "C" NOT NULL,
    seq BIGINT NOT NULL,
    stamp DOUBLE PRECISION NOT NULL,
    x DOUBLE PRECISION NOT NULL,
    y DOUBLE PRECISION NOT NULL,
    theta DOUBLE PRECISION NOT NULL,
    PRIMARY KEY (map_id, robot, seq)
);
CREATE TABLE IF NOT EXISTS events (
    map_id TEXT COLLATE "C" NOT NULL,
    id BIGINT NOT NULL,
    kind TEXT NOT NULL,
    data TEXT NOT NULL,
    created DOUBLE PRECISION NOT NULL,
    PRIMARY KEY (map_id, id)
);
"""

_schema_done: set[str] = set()
_schema_lock = threading.Lock()


def redact(url: str) -> str:
    """The URL without its password (for logs)."""
    parts = urlsplit(url)
    if parts.password is None:
        return url
    netloc = parts.netloc.replace(f":{parts.password}@", ":***@", 1)
    return urlunsplit(parts._replace(netloc=netloc))


def connect(url: str) -> psycopg.Connection[Any]:
    """An autocommit connection, the schema created on first use in this process."""
    if psycopg is None:
        raise RuntimeError("a postgresql:// store needs psycopg 3: pip install 'covslam[postgres]'")
    conn = psycopg.connect(url, autocommit=True)
    with _schema_lock:
        if url not in _schema_done:
            with conn.transaction():
                conn.execute("SELECT pg_advisory_xact_lock(%s)", (_SCHEMA_LOCK,))
                conn.execute(_SCHEMA.encode())
            _schema_done.add(url)
    return conn


class _Shared:
    """One connection shared by the threads of a process (catalogue, event reads),
    re-opened when the server went away (a statement that met a cut connection is
    sent once more on the new one)."""

    def __init__(self, url: str) -> None:
        self._url = url
        self.conn = connect(url)
        self._lock = threading.Lock()

    def execute(self, sql: str, args: Any = (), *, fetch: str = "none") -> Any:
        """Run one statement; `fetch` "all" (rows), "one" (a row or None) or "none"."""
        with self._lock:
            for attempt in (0, 1):
                try:
                    if self.conn.closed or self.conn.broken:
                        self.conn = connect(self._url)
                    cur = self.conn.execute(sql, args)
                    if fetch == "all":
                        return cur.fetchall()
                    return cur.fetchone() if fetch == "one" else None
                except CONNECTION_ERRORS:
                    if attempt:
                        raise
            return None  # not reached

    def close(self) -> None:
        with self._lock:
            self.conn.close()


# --------------------------------------------------------------------------- catalogue


class PgCatalog(Catalog):
    """The list of maps, table ``maps``, and their API keys, table ``keys``."""

    def __init__(self, shared: _Shared) -> None:
        self._db = shared

    def close(self) -> None:
        """The connection belongs to the store."""

    def _rows(self, sql: str, args: Args) -> list[Any]:
        rows: list[Any] = self._db.execute(pyformat(sql), args, fetch="all")
        return rows

    def _write(self, sql: str, args: Args) -> None:
        self._db.execute(pyformat(sql), args)

    def remove(self, map_id: str) -> None:
        """Delete a map's record and its keys (one statement, so all or nothing)."""
        self._db.execute(
            "WITH k AS (DELETE FROM keys WHERE map_id = %(m)s) DELETE FROM maps WHERE id = %(m)s",
            {"m": map_id},
        )


# --------------------------------------------------------------------------- one map


class PgMapStore(MapStore):
    """One map's rows (service.store_sql.MapStore), on a connection of its own."""

    META = "map_meta"
    NO_LIMIT = None
    # the json type (not jsonb) keeps a value's text as the worker wrote it
    FRAME_STATS = (
        "SELECT id, robot, seq, r -> 'landmarks' ->> 'live', "
        "(r -> 'landmarks' -> 'added')::text, (r -> 'landmarks' -> 'marginalised')::text, "
        "(r -> 'timing_ms' ->> 'total')::float8, (r -> 'covariance')::text "
        "FROM (SELECT id, robot, seq, result::json AS r FROM frames "
        "WHERE map_id = :m AND result IS NOT NULL) f ORDER BY id"
    )
    REMOVED_LABELS = "SELECT DISTINCT landmark_id, record::json ->> 'label' FROM removal_log{only}"

    def __init__(self, url: str, map_id: str) -> None:
        self.map_id = map_id
        self._conn = connect(url)

    def close(self) -> None:
        self._conn.close()

    def _rows(self, sql: str, args: Args) -> list[Any]:
        return self._conn.execute(pyformat(sql), args).fetchall()

    def _write(self, sql: str, args: Args) -> None:
        self._conn.execute(pyformat(sql), args)

    def _insert(self, sql: str, args: Args) -> int:
        row = self._conn.execute(pyformat(sql + " RETURNING id"), args).fetchone()
        assert row is not None
        return int(row[0])

    def _many(self, sql: str, rows: Sequence[Args]) -> None:
        with self._conn.cursor() as cur:
            cur.executemany(pyformat(sql), rows)

    def _transaction(self) -> AbstractContextManager[Any]:
        return self._conn.transaction()

    def checkpoint(self) -> None:
        """Nothing to fold: PostgreSQL manages its own WAL."""


class PgMap:
    """A map's rows in the database (service.store.MapPlace)."""

    def __init__(self, store: PgStore, map_id: str) -> None:
        self._store = store
        self.map_id = map_id

    def __str__(self) -> str:
        return f"{self.map_id} in {self._store.description}"

    def exists(self) -> bool:
        row = self._store.shared.execute(
            "SELECT 1 FROM map_meta WHERE map_id = %s", (self.map_id,), fetch="one"
        )
        return row is not None

    def open(self) -> PgMapStore:
        return PgMapStore(self._store.url, self.map_id)

    def remove(self) -> None:
        # one statement, so all or nothing
        *first, last = _MAP_TABLES
        ctes = ", ".join(
            f"d{i} AS (DELETE FROM {t} WHERE map_id = %(m)s)" for i, t in enumerate(first)
        )
        self._store.shared.execute(
            f"WITH {ctes} DELETE FROM {last} WHERE map_id = %(m)s", {"m": self.map_id}
        )


class PgStore(MapReads):
    """A PostgreSQL database holding the catalogue and every map (service.store.Store)."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.description = f"PostgreSQL at {redact(url)}"
        self.shared = _Shared(url)

    def catalog(self) -> PgCatalog:
        return PgCatalog(self.shared)

    def place(self, map_id: str) -> PgMap:
        return PgMap(self, map_id)

    def _read(self, map_id: str, sql: str, args: Args) -> list[Any]:
        rows: list[Any] = self.shared.execute(pyformat(sql), args, fetch="all")
        return rows

    def close(self) -> None:
        self.shared.close()
