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

import json
import threading
import time
from collections.abc import Sequence
from typing import Any
from urllib.parse import urlsplit, urlunsplit

import numpy as np
from numpy.typing import NDArray

from graph.trajectory import PoseRow
from service.store import FrameFigures, KeyRecord, MapRecord, StoredFrame

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


def _next_id(table: str) -> str:
    """SQL of the next per-map id of `table` (its map id is the next parameter)."""
    return f"(SELECT coalesce(max(id), 0) + 1 FROM {table} WHERE map_id = %s)"


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


class PgCatalog:
    """The list of maps, table ``maps``, and their API keys, table ``keys``."""

    def __init__(self, shared: _Shared) -> None:
        self._db = shared

    def close(self) -> None:
        """The connection belongs to the store."""

    def add(self, record: MapRecord) -> None:
        self._db.execute(
            "INSERT INTO maps (id, name, mode, config, created) VALUES (%s, %s, %s, %s, %s)",
            (record.id, record.name, record.mode, json.dumps(record.config), record.created),
        )

    def remove(self, map_id: str) -> None:
        """Delete a map's record and its keys (one statement, so all or nothing)."""
        self._db.execute(
            "WITH k AS (DELETE FROM keys WHERE map_id = %(m)s) DELETE FROM maps WHERE id = %(m)s",
            {"m": map_id},
        )

    def set_mode(self, map_id: str, mode: str) -> None:
        self._db.execute("UPDATE maps SET mode = %s WHERE id = %s", (mode, map_id))

    def all(self) -> list[MapRecord]:
        rows = self._db.execute(
            "SELECT id, name, mode, config, created FROM maps ORDER BY created, id", fetch="all"
        )
        return [MapRecord(r[0], r[1], r[2], json.loads(r[3]), r[4]) for r in rows]

    def get(self, map_id: str) -> MapRecord | None:
        r = self._db.execute(
            "SELECT id, name, mode, config, created FROM maps WHERE id = %s", (map_id,), fetch="one"
        )
        return None if r is None else MapRecord(r[0], r[1], r[2], json.loads(r[3]), r[4])

    def add_key(self, key: KeyRecord) -> None:
        self._db.execute(
            "INSERT INTO keys (id, map_id, scope, hash, created) VALUES (%s, %s, %s, %s, %s)",
            (key.id, key.map_id, key.scope, key.hash, key.created),
        )

    def remove_key(self, key_id: str) -> None:
        self._db.execute("DELETE FROM keys WHERE id = %s", (key_id,))

    def keys(self) -> list[KeyRecord]:
        rows = self._db.execute(
            "SELECT id, map_id, scope, hash, created FROM keys ORDER BY created, id", fetch="all"
        )
        return [KeyRecord(*r) for r in rows]


# --------------------------------------------------------------------------- one map


class PgMapStore:
    """One map's rows (service.store.MapStore), on a connection of its own."""

    def __init__(self, url: str, map_id: str) -> None:
        self.map_id = map_id
        self._conn = connect(url)

    def close(self) -> None:
        self._conn.close()

    def _one(self, sql: str, args: Sequence[Any]) -> Any:
        row = self._conn.execute(sql, args).fetchone()
        return None if row is None else row[0]

    # meta
    def get_meta(self, key: str) -> Any | None:
        value = self._one(
            "SELECT value FROM map_meta WHERE map_id = %s AND key = %s", (self.map_id, key)
        )
        return None if value is None else json.loads(value)

    def set_meta(self, key: str, value: Any) -> None:
        self._conn.execute(
            "INSERT INTO map_meta (map_id, key, value) VALUES (%s, %s, %s) "
            "ON CONFLICT (map_id, key) DO UPDATE SET value = excluded.value",
            (self.map_id, key, json.dumps(value)),
        )

    # the frame log
    def find_frame(self, robot: str, seq: int) -> StoredFrame | None:
        row = self._conn.execute(
            "SELECT id, robot, seq, body, result, attempts FROM frames "
            "WHERE map_id = %s AND robot = %s AND seq = %s",
            (self.map_id, robot, seq),
        ).fetchone()
        return None if row is None else StoredFrame(*row)

    def append_frame(
        self,
        robot: str,
        seq: int,
        body: str,
        image: bytes | None = None,
        observations: str | None = None,
    ) -> int:
        m = self.map_id
        with self._conn.transaction():
            frame_id = int(
                self._one(
                    "INSERT INTO frames (map_id, id, robot, seq, body, received) "
                    f"VALUES (%s, {_next_id('frames')}, %s, %s, %s, %s) RETURNING id",
                    (m, m, robot, seq, body, time.time()),
                )
            )
            if image is not None:
                self._conn.execute(
                    "INSERT INTO images (map_id, frame_id, data) VALUES (%s, %s, %s)",
                    (m, frame_id, image),
                )
            if observations is not None:
                self._conn.execute(
                    "INSERT INTO image_observations (map_id, frame_id, observations) "
                    "VALUES (%s, %s, %s)",
                    (m, frame_id, observations),
                )
        return frame_id

    def frame_image(self, frame_id: int) -> bytes | None:
        data = self._one(
            "SELECT data FROM images WHERE map_id = %s AND frame_id = %s", (self.map_id, frame_id)
        )
        return None if data is None else bytes(data)

    def image_observations(self, frame_id: int) -> list[Any] | None:
        text = self._one(
            "SELECT observations FROM image_observations WHERE map_id = %s AND frame_id = %s",
            (self.map_id, frame_id),
        )
        return None if text is None else list(json.loads(text))

    def count_attempt(self, frame_id: int) -> None:
        self._conn.execute(
            "UPDATE frames SET attempts = attempts + 1 WHERE map_id = %s AND id = %s",
            (self.map_id, frame_id),
        )

    def delete_frame(self, frame_id: int) -> None:
        with self._conn.transaction():
            self._conn.execute(
                "DELETE FROM frames WHERE map_id = %s AND id = %s", (self.map_id, frame_id)
            )
            for table in ("images", "image_observations"):
                self._conn.execute(
                    f"DELETE FROM {table} WHERE map_id = %s AND frame_id = %s",
                    (self.map_id, frame_id),
                )

    def complete_frame(
        self,
        frame_id: int,
        result: str,
        events: list[tuple[str, str]],
        removals: list[tuple[int, int, str]],
        observations: str | None = None,
        poses: list[PoseRow] | None = None,
        *,
        archived: Sequence[tuple[int, int, str]] = (),
        restored: Sequence[int] = (),
    ) -> list[int]:
        m, now = self.map_id, time.time()
        with self._conn.transaction(), self._conn.cursor() as cur:
            cur.execute(
                "UPDATE frames SET result = %s WHERE map_id = %s AND id = %s",
                (result, m, frame_id),
            )
            if observations is not None:
                cur.execute(
                    "INSERT INTO image_observations (map_id, frame_id, observations) "
                    "VALUES (%s, %s, %s) ON CONFLICT (map_id, frame_id) "
                    "DO UPDATE SET observations = excluded.observations",
                    (m, frame_id, observations),
                )
            if removals:
                cur.executemany(
                    "INSERT INTO removal_log (map_id, landmark_id, frame, record) "
                    "VALUES (%s, %s, %s, %s) ON CONFLICT DO NOTHING",
                    [(m, *r) for r in removals],
                )
            if restored:
                cur.execute(
                    "DELETE FROM archive WHERE map_id = %s AND landmark_id = ANY(%s)",
                    (m, list(restored)),
                )
            if archived:
                cur.executemany(
                    "INSERT INTO archive (map_id, landmark_id, frame, record) "
                    "VALUES (%s, %s, %s, %s) ON CONFLICT (map_id, landmark_id) "
                    "DO UPDATE SET frame = excluded.frame, record = excluded.record",
                    [(m, *a) for a in archived],
                )
            if poses:
                self._put_poses(cur, poses)
            return [self._insert_event(cur, kind, data, now) for kind, data in events]

    def _insert_event(self, cur: psycopg.Cursor[Any], kind: str, data: str, now: float) -> int:
        cur.execute(
            "INSERT INTO events (map_id, id, kind, data, created) "
            f"VALUES (%s, {_next_id('events')}, %s, %s, %s) RETURNING id",
            (self.map_id, self.map_id, kind, data, now),
        )
        row = cur.fetchone()
        assert row is not None
        return int(row[0])

    def add_event(self, kind: str, data: str) -> int:
        with self._conn.cursor() as cur:
            return self._insert_event(cur, kind, data, time.time())

    def frames_after(self, frame_id: int) -> list[StoredFrame]:
        rows = self._conn.execute(
            "SELECT id, robot, seq, body, result, attempts FROM frames "
            "WHERE map_id = %s AND id > %s ORDER BY id",
            (self.map_id, frame_id),
        ).fetchall()
        return [StoredFrame(*r) for r in rows]

    def frame_count(self) -> int:
        return int(self._one("SELECT count(*) FROM frames WHERE map_id = %s", (self.map_id,)))

    def frame_stats(self) -> list[FrameFigures]:
        # the json type (not jsonb) keeps a value's text as the worker wrote it
        rows = self._conn.execute(
            "SELECT id, robot, seq, r -> 'landmarks' ->> 'live', "
            "(r -> 'landmarks' -> 'added')::text, (r -> 'landmarks' -> 'marginalised')::text, "
            "(r -> 'timing_ms' ->> 'total')::float8, (r -> 'covariance')::text "
            "FROM (SELECT id, robot, seq, result::json AS r FROM frames "
            "WHERE map_id = %s AND result IS NOT NULL) f ORDER BY id",
            (self.map_id,),
        ).fetchall()
        return [FrameFigures.from_row(tuple(r)) for r in rows]

    # final trajectory rows
    def _put_poses(self, cur: psycopg.Cursor[Any], rows: list[PoseRow]) -> None:
        cur.executemany(
            "INSERT INTO poses (map_id, robot, seq, stamp, x, y, theta) "
            "VALUES (%s, %s, %s, %s, %s, %s, %s) ON CONFLICT (map_id, robot, seq) DO UPDATE "
            "SET stamp = excluded.stamp, x = excluded.x, y = excluded.y, theta = excluded.theta",
            [(self.map_id, r.robot, r.seq, r.stamp, r.x, r.y, r.theta) for r in rows],
        )

    def put_poses(self, rows: list[PoseRow]) -> None:
        if rows:
            with self._conn.transaction(), self._conn.cursor() as cur:
                self._put_poses(cur, rows)

    def poses(self, robot: str | None = None) -> dict[str, NDArray[np.float64]]:
        sql = "SELECT robot, seq, stamp, x, y, theta FROM poses WHERE map_id = %s"
        args: tuple[str, ...] = (self.map_id,)
        if robot is not None:
            sql, args = sql + " AND robot = %s", (self.map_id, robot)
        out: dict[str, list[tuple[float, ...]]] = {}
        for name, *values in self._conn.execute(sql + " ORDER BY robot, seq", args):
            out.setdefault(str(name), []).append(tuple(values))
        return {k: np.array(v, dtype=np.float64).reshape(-1, 5) for k, v in out.items()}

    def pose_positions(self) -> NDArray[np.float64]:
        rows = self._conn.execute(
            "SELECT x, y FROM poses WHERE map_id = %s", (self.map_id,)
        ).fetchall()
        return np.array(rows, dtype=np.float64).reshape(-1, 2)

    def pose_count(self) -> int:
        return int(self._one("SELECT count(*) FROM poses WHERE map_id = %s", (self.map_id,)))

    # snapshots
    def save_snapshot(
        self,
        upto: int,
        state: bytes,
        *,
        keep: int,
        frontend: bytes | None = None,
        prune_images: bool = False,
    ) -> None:
        m = self.map_id
        with self._conn.transaction():
            snapshot_id = self._one(
                "INSERT INTO snapshots (map_id, id, upto, created, state) "
                f"VALUES (%s, {_next_id('snapshots')}, %s, %s, %s) RETURNING id",
                (m, m, upto, time.time(), state),
            )
            if frontend is not None:
                self._conn.execute(
                    "INSERT INTO frontend_states (map_id, snapshot_id, state) VALUES (%s, %s, %s)",
                    (m, snapshot_id, frontend),
                )
            self._conn.execute(
                "DELETE FROM snapshots WHERE map_id = %s AND id NOT IN "
                "(SELECT id FROM snapshots WHERE map_id = %s ORDER BY id DESC LIMIT %s)",
                (m, m, keep),
            )
            self._conn.execute(
                "DELETE FROM frontend_states f WHERE map_id = %s AND NOT EXISTS "
                "(SELECT 1 FROM snapshots s WHERE s.map_id = f.map_id AND s.id = f.snapshot_id)",
                (m,),
            )
            if prune_images:
                self._conn.execute(
                    "DELETE FROM images WHERE map_id = %s "
                    "AND frame_id <= (SELECT min(upto) FROM snapshots WHERE map_id = %s) "
                    "AND frame_id IN (SELECT frame_id FROM image_observations WHERE map_id = %s)",
                    (m, m, m),
                )

    def checkpoint(self) -> None:
        """Nothing to fold: PostgreSQL manages its own WAL."""

    def image_count(self) -> int:
        return int(self._one("SELECT count(*) FROM images WHERE map_id = %s", (self.map_id,)))

    def latest_snapshot(self) -> tuple[int, bytes] | None:
        row = self._conn.execute(
            "SELECT upto, state FROM snapshots WHERE map_id = %s ORDER BY id DESC LIMIT 1",
            (self.map_id,),
        ).fetchone()
        return None if row is None else (int(row[0]), bytes(row[1]))

    def latest_frontend_state(self) -> bytes | None:
        state = self._one(
            "SELECT f.state FROM frontend_states f WHERE f.map_id = %s "
            "AND f.snapshot_id = (SELECT max(id) FROM snapshots WHERE map_id = %s)",
            (self.map_id, self.map_id),
        )
        return None if state is None else bytes(state)

    # removals and events
    def removals(self, limit: int | None = None) -> list[dict[str, Any]]:
        rows = self._conn.execute(
            "SELECT record FROM (SELECT frame, landmark_id, record FROM removal_log "
            "WHERE map_id = %s ORDER BY frame DESC, landmark_id DESC LIMIT %s) r "
            "ORDER BY frame, landmark_id",
            (self.map_id, limit),
        ).fetchall()
        return [json.loads(r[0]) for r in rows]

    def removed_labels(self) -> dict[int, str]:
        rows = self._conn.execute(
            "SELECT DISTINCT landmark_id, record::json ->> 'label' FROM removal_log "
            "WHERE map_id = %s",
            (self.map_id,),
        ).fetchall()
        return {int(i): str(label) for i, label in rows}

    def removal_count(self) -> int:
        return int(self._one("SELECT count(*) FROM removal_log WHERE map_id = %s", (self.map_id,)))

    def archived(self) -> list[dict[str, Any]]:
        rows = self._conn.execute(
            "SELECT record FROM archive WHERE map_id = %s ORDER BY landmark_id",
            (self.map_id,),
        ).fetchall()
        return [json.loads(r[0]) for r in rows]

    def prune_events(self, keep: int) -> None:
        self._conn.execute(
            "DELETE FROM events WHERE map_id = %s "
            "AND id <= (SELECT max(id) FROM events WHERE map_id = %s) - %s",
            (self.map_id, self.map_id, keep),
        )


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


class PgStore:
    """A PostgreSQL database holding the catalogue and every map (service.store.Store)."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.description = f"PostgreSQL at {redact(url)}"
        self.shared = _Shared(url)

    def catalog(self) -> PgCatalog:
        return PgCatalog(self.shared)

    def place(self, map_id: str) -> PgMap:
        return PgMap(self, map_id)

    def read_events(self, map_id: str, after: int, limit: int = 500) -> list[tuple[int, str, str]]:
        rows = self.shared.execute(
            "SELECT id, kind, data FROM events WHERE map_id = %s AND id > %s ORDER BY id LIMIT %s",
            (map_id, after, limit),
            fetch="all",
        )
        return [(int(r[0]), str(r[1]), str(r[2])) for r in rows]

    def latest_event_id(self, map_id: str) -> int:
        row = self.shared.execute(
            "SELECT max(id) FROM events WHERE map_id = %s", (map_id,), fetch="one"
        )
        return int(row[0] or 0) if row is not None else 0

    def close(self) -> None:
        self.shared.close()
