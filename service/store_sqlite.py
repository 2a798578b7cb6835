"""The embedded SQLite store (service.store): a catalogue, and one database file per map.

Layout under the data directory::

    catalog.sqlite          maps(id, name, mode, config, created),
                            keys(id, map_id, scope, hash, created): API keys, hashed
    maps/<id>.sqlite        frames (the durable log), snapshots, removal log, archive,
                            events, meta

Every database runs in WAL mode; ``synchronous`` is NORMAL (survives a killed
process: a commit is in the OS before it returns) or FULL (also survives power
loss, one fsync per commit). The catalogue is written by the API process, a map's
file only by the worker process that owns the map; anyone may read.

The frame log: a frame is appended (and committed) before it is processed; its
result, its events and the removals it caused are written together in one
transaction afterwards. ``UNIQUE(robot, seq)`` backs idempotent retries. An image
frame's encoded image is appended in the same transaction as its log row (table
``images``), so replaying the log reproduces the map; a snapshot of a camera map
carries the front end's state (``frontend_states``, same transaction). The labelled
observations the front end made of an image are stored with the frame's result
(``image_observations``): an export carries them instead of the image, and once
every kept snapshot covers a frame its image may be deleted (``prune_images``), so a
camera map's file stops growing by an image a frame.

The trajectory rows the estimator will not change again (their poses were
marginalised, graph.trajectory) are written to ``poses`` with the frame that
finalised them, and the estimator forgets them: its memory and its snapshots hold
only the rows still in play. ``poses`` is keyed by (robot, seq), so a replay of the
log that finalises a row again replaces it.

``removal_log`` and ``archive``: see service.store. ``removals`` is the older, one row
per landmark, form of the removal log; a file that still has rows in it has them moved
into ``removal_log`` when it is opened.
"""

from __future__ import annotations

import json
import shutil
import sqlite3
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from graph.trajectory import PoseRow
from service.store import FrameFigures, KeyRecord, MapRecord, StoredFrame

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


# --------------------------------------------------------------------------- catalogue


class SqliteCatalog:
    """The list of maps and their API keys (API process): ``catalog.sqlite`` in the data
    directory."""

    def __init__(self, data_dir: Path, *, synchronous: str) -> None:
        data_dir.mkdir(parents=True, exist_ok=True)
        self._conn = connect(data_dir / "catalog.sqlite", synchronous=synchronous)
        self._conn.executescript(_CATALOG_SCHEMA)

    def close(self) -> None:
        self._conn.close()

    def add(self, record: MapRecord) -> None:
        with transaction(self._conn):
            self._conn.execute(
                "INSERT INTO maps (id, name, mode, config, created) VALUES (?, ?, ?, ?, ?)",
                (record.id, record.name, record.mode, json.dumps(record.config), record.created),
            )

    def remove(self, map_id: str) -> None:
        """Delete a map's record and its keys."""
        with transaction(self._conn):
            self._conn.execute("DELETE FROM maps WHERE id = ?", (map_id,))
            self._conn.execute("DELETE FROM keys WHERE map_id = ?", (map_id,))

    def set_mode(self, map_id: str, mode: str) -> None:
        with transaction(self._conn):
            self._conn.execute("UPDATE maps SET mode = ? WHERE id = ?", (mode, map_id))

    def all(self) -> list[MapRecord]:
        rows = self._conn.execute(
            "SELECT id, name, mode, config, created FROM maps ORDER BY created, id"
        ).fetchall()
        return [MapRecord(r[0], r[1], r[2], json.loads(r[3]), r[4]) for r in rows]

    def get(self, map_id: str) -> MapRecord | None:
        r = self._conn.execute(
            "SELECT id, name, mode, config, created FROM maps WHERE id = ?", (map_id,)
        ).fetchone()
        return None if r is None else MapRecord(r[0], r[1], r[2], json.loads(r[3]), r[4])

    def add_key(self, key: KeyRecord) -> None:
        with transaction(self._conn):
            self._conn.execute(
                "INSERT INTO keys (id, map_id, scope, hash, created) VALUES (?, ?, ?, ?, ?)",
                (key.id, key.map_id, key.scope, key.hash, key.created),
            )

    def remove_key(self, key_id: str) -> None:
        with transaction(self._conn):
            self._conn.execute("DELETE FROM keys WHERE id = ?", (key_id,))

    def keys(self) -> list[KeyRecord]:
        rows = self._conn.execute(
            "SELECT id, map_id, scope, hash, created FROM keys ORDER BY created, id"
        ).fetchall()
        return [KeyRecord(*r) for r in rows]


# --------------------------------------------------------------------------- one map


class SqliteMapStore:
    """One map's database file (owned by its worker process)."""

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

    def close(self) -> None:
        self._conn.close()

    # meta
    def get_meta(self, key: str) -> Any | None:
        row = self._conn.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return None if row is None else json.loads(row[0])

    def set_meta(self, key: str, value: Any) -> None:
        with transaction(self._conn):
            self._conn.execute(
                "INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)", (key, json.dumps(value))
            )

    # the frame log
    def find_frame(self, robot: str, seq: int) -> StoredFrame | None:
        row = self._conn.execute(
            "SELECT id, robot, seq, body, result, attempts FROM frames WHERE robot = ? AND seq = ?",
            (robot, seq),
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
        """Append an accepted frame (and its encoded image, or for an imported image frame
        the observations its image gave) to the log and commit; its log id."""
        with transaction(self._conn):
            cur = self._conn.execute(
                "INSERT INTO frames (robot, seq, body, received) VALUES (?, ?, ?, ?)",
                (robot, seq, body, time.time()),
            )
            assert cur.lastrowid is not None
            if image is not None:
                self._conn.execute(
                    "INSERT INTO images (frame_id, data) VALUES (?, ?)", (cur.lastrowid, image)
                )
            if observations is not None:
                self._conn.execute(
                    "INSERT INTO image_observations (frame_id, observations) VALUES (?, ?)",
                    (cur.lastrowid, observations),
                )
        return cur.lastrowid

    def frame_image(self, frame_id: int) -> bytes | None:
        """The encoded image of a logged image frame (None for a frame without one)."""
        row = self._conn.execute(
            "SELECT data FROM images WHERE frame_id = ?", (frame_id,)
        ).fetchone()
        return None if row is None else bytes(row[0])

    def image_observations(self, frame_id: int) -> list[Any] | None:
        """The labelled observations a logged image frame's image gave (None: not stored)."""
        row = self._conn.execute(
            "SELECT observations FROM image_observations WHERE frame_id = ?", (frame_id,)
        ).fetchone()
        return None if row is None else list(json.loads(row[0]))

    def count_attempt(self, frame_id: int) -> None:
        """Note (durably) that an unfinished frame is about to be processed again."""
        with transaction(self._conn):
            self._conn.execute(
                "UPDATE frames SET attempts = attempts + 1 WHERE id = ?", (frame_id,)
            )

    def delete_frame(self, frame_id: int) -> None:
        with transaction(self._conn):
            self._conn.execute("DELETE FROM frames WHERE id = ?", (frame_id,))
            self._conn.execute("DELETE FROM images WHERE frame_id = ?", (frame_id,))
            self._conn.execute("DELETE FROM image_observations WHERE frame_id = ?", (frame_id,))

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
        now = time.time()
        ids: list[int] = []
        with transaction(self._conn):
            self._conn.execute("UPDATE frames SET result = ? WHERE id = ?", (result, frame_id))
            if observations is not None:
                self._conn.execute(
                    "INSERT OR REPLACE INTO image_observations (frame_id, observations) "
                    "VALUES (?, ?)",
                    (frame_id, observations),
                )
            self._conn.executemany(
                "INSERT OR IGNORE INTO removal_log (landmark_id, frame, record) VALUES (?, ?, ?)",
                removals,
            )
            self._conn.executemany(
                "DELETE FROM archive WHERE landmark_id = ?", [(lid,) for lid in restored]
            )
            self._conn.executemany(
                "INSERT OR REPLACE INTO archive (landmark_id, frame, record) VALUES (?, ?, ?)",
                archived,
            )
            if poses:
                self._put_poses(poses)
            for kind, data in events:
                cur = self._conn.execute(
                    "INSERT INTO events (kind, data, created) VALUES (?, ?, ?)", (kind, data, now)
                )
                assert cur.lastrowid is not None
                ids.append(cur.lastrowid)
        return ids

    def add_event(self, kind: str, data: str) -> int:
        with transaction(self._conn):
            cur = self._conn.execute(
                "INSERT INTO events (kind, data, created) VALUES (?, ?, ?)",
                (kind, data, time.time()),
            )
        assert cur.lastrowid is not None
        return cur.lastrowid

    def frames_after(self, frame_id: int) -> list[StoredFrame]:
        rows = self._conn.execute(
            "SELECT id, robot, seq, body, result, attempts FROM frames WHERE id > ? ORDER BY id",
            (frame_id,),
        ).fetchall()
        return [StoredFrame(*r) for r in rows]

    def frame_count(self) -> int:
        return int(self._conn.execute("SELECT count(*) FROM frames").fetchone()[0])

    def frame_stats(self) -> list[FrameFigures]:
        """Figures of every processed frame from its stored result, in log order
        (picked out by SQLite's json_extract; the covariance is left as JSON text)."""
        rows = self._conn.execute(
            "SELECT id, robot, seq, json_extract(result, '$.landmarks.live'), "
            "json_extract(result, '$.landmarks.added'), "
            "json_extract(result, '$.landmarks.marginalised'), "
            "json_extract(result, '$.timing_ms.total'), json_extract(result, '$.covariance') "
            "FROM frames WHERE result IS NOT NULL ORDER BY id"
        ).fetchall()
        return [FrameFigures.from_row(tuple(r)) for r in rows]

    # final trajectory rows
    def _put_poses(self, rows: list[PoseRow]) -> None:
        self._conn.executemany(
            "INSERT OR REPLACE INTO poses (robot, seq, stamp, x, y, theta) "
            "VALUES (?, ?, ?, ?, ?, ?)",
            [(r.robot, r.seq, r.stamp, r.x, r.y, r.theta) for r in rows],
        )

    def put_poses(self, rows: list[PoseRow]) -> None:
        """Store final trajectory rows (replacing those of the same robot and seq)."""
        if rows:
            with transaction(self._conn):
                self._put_poses(rows)

    def poses(self, robot: str | None = None) -> dict[str, NDArray[np.float64]]:
        """Stored final rows per robot (`robot`: that one only), each an (N, 5) array
        seq, stamp, x, y, theta sorted by seq (as BearingSlam.trajectory)."""
        sql = "SELECT robot, seq, stamp, x, y, theta FROM poses"
        args: tuple[str, ...] = ()
        if robot is not None:
            sql, args = sql + " WHERE robot = ?", (robot,)
        out: dict[str, list[tuple[float, ...]]] = {}
        for name, *values in self._conn.execute(sql + " ORDER BY robot, seq", args):
            out.setdefault(str(name), []).append(tuple(values))
        return {k: np.array(v, dtype=np.float64).reshape(-1, 5) for k, v in out.items()}

    def pose_positions(self) -> NDArray[np.float64]:
        """(N, 2) x, y of every stored final row, metres."""
        rows = self._conn.execute("SELECT x, y FROM poses").fetchall()
        return np.array(rows, dtype=np.float64).reshape(-1, 2)

    def pose_count(self) -> int:
        return int(self._conn.execute("SELECT count(*) FROM poses").fetchone()[0])

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
        """Store a snapshot (and the front end's state with it); keep the newest `keep`.

        `prune_images`: also delete the images of frames that every kept snapshot
        covers and whose observations are stored (what a replay of such a frame, or
        an export, uses instead of the image). Deleted pages are reused by later
        inserts, so the file's size levels off."""
        with transaction(self._conn):
            cur = self._conn.execute(
                "INSERT INTO snapshots (upto, created, state) VALUES (?, ?, ?)",
                (upto, time.time(), state),
            )
            if frontend is not None:
                self._conn.execute(
                    "INSERT INTO frontend_states (snapshot_id, state) VALUES (?, ?)",
                    (cur.lastrowid, frontend),
                )
            self._conn.execute(
                "DELETE FROM snapshots WHERE id NOT IN "
                "(SELECT id FROM snapshots ORDER BY id DESC LIMIT ?)",
                (keep,),
            )
            self._conn.execute(
                "DELETE FROM frontend_states WHERE snapshot_id NOT IN (SELECT id FROM snapshots)"
            )
            if prune_images:
                self._conn.execute(
                    "DELETE FROM images WHERE frame_id <= (SELECT min(upto) FROM snapshots) "
                    "AND frame_id IN (SELECT frame_id FROM image_observations)"
                )

    def checkpoint(self) -> None:
        """Fold the WAL into the database file (so its size on disk says what it holds)."""
        self._conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")

    def image_count(self) -> int:
        """Images stored in the log."""
        return int(self._conn.execute("SELECT count(*) FROM images").fetchone()[0])

    def latest_snapshot(self) -> tuple[int, bytes] | None:
        row = self._conn.execute(
            "SELECT upto, state FROM snapshots ORDER BY id DESC LIMIT 1"
        ).fetchone()
        return None if row is None else (int(row[0]), bytes(row[1]))

    def latest_frontend_state(self) -> bytes | None:
        """The front end's state stored with the latest snapshot (None if it has none)."""
        row = self._conn.execute(
            "SELECT f.state FROM snapshots s JOIN frontend_states f ON f.snapshot_id = s.id "
            "WHERE s.id = (SELECT max(id) FROM snapshots)"
        ).fetchone()
        return None if row is None else bytes(row[0])

    # removals and events
    def removals(self, limit: int | None = None) -> list[dict[str, Any]]:
        """The most recent `limit` removals (all if None), oldest first."""
        rows = self._conn.execute(
            "SELECT record FROM (SELECT frame, landmark_id, record FROM removal_log "
            "ORDER BY frame DESC, landmark_id DESC LIMIT ?) ORDER BY frame, landmark_id",
            (-1 if limit is None else limit,),
        ).fetchall()
        return [json.loads(r[0]) for r in rows]

    def removed_labels(self) -> dict[int, str]:
        """Label of every landmark in the removal log, by landmark id."""
        rows = self._conn.execute(
            "SELECT DISTINCT landmark_id, json_extract(record, '$.label') FROM removal_log"
        ).fetchall()
        return {int(i): str(label) for i, label in rows}

    def removal_count(self) -> int:
        return int(self._conn.execute("SELECT count(*) FROM removal_log").fetchone()[0])

    def archived(self) -> list[dict[str, Any]]:
        rows = self._conn.execute("SELECT record FROM archive ORDER BY landmark_id").fetchall()
        return [json.loads(r[0]) for r in rows]

    def prune_events(self, keep: int) -> None:
        with transaction(self._conn):
            self._conn.execute(
                "DELETE FROM events WHERE id <= (SELECT max(id) FROM events) - ?", (keep,)
            )


def read_events(path: Path, after: int, limit: int = 500) -> list[tuple[int, str, str]]:
    """Events with id > `after` from a map's database: (id, kind, data JSON), oldest first."""
    if not path.exists():
        return []
    conn = connect(path, synchronous="NORMAL", readonly=True)
    try:
        rows = conn.execute(
            "SELECT id, kind, data FROM events WHERE id > ? ORDER BY id LIMIT ?", (after, limit)
        ).fetchall()
    finally:
        conn.close()
    return [(int(r[0]), str(r[1]), str(r[2])) for r in rows]


def latest_event_id(path: Path) -> int:
    """The id of a map's newest event (0 if none)."""
    if not path.exists():
        return 0
    conn = connect(path, synchronous="NORMAL", readonly=True)
    try:
        row = conn.execute("SELECT max(id) FROM events").fetchone()
    finally:
        conn.close()
    return int(row[0] or 0)


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


class SqliteStore:
    """The embedded store under a data directory (service.store.Store)."""

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

    def read_events(self, map_id: str, after: int, limit: int = 500) -> list[tuple[int, str, str]]:
        return read_events(map_db_path(self.data_dir, map_id), after, limit)

    def latest_event_id(self, map_id: str) -> int:
        return latest_event_id(map_db_path(self.data_dir, map_id))

    def close(self) -> None:
        """Nothing to close: each call opens its own connection."""
