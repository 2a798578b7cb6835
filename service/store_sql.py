"""The catalogue and a map's store, with the SQL both backends run written once.

The SQLite store keeps one database file per map; the PostgreSQL store keeps every map
in one database, each table with a leading ``map_id`` column. A statement is written
once, with named parameters (``:name``) and these fields for where the two differ:

``{m}``     the map's rows, as the first condition of a WHERE (``map_id = :m AND`` or
            nothing);
``{only}``  the map's rows as a whole WHERE clause (`` WHERE map_id = :m`` or nothing);
``{mc}``    the map id column in a column list or conflict target (``map_id,`` or
            nothing), ``{mv}`` its value in a VALUES list (``:m,`` or nothing);
``{idc}``, ``{idv}``  a new row's id where the store numbers rows itself (PostgreSQL:
            ``max(id) + 1`` of the map's rows; SQLite: its row ids do the same);
``{meta}``  the table of a map's meta values.

A backend gives its connection's primitives (`_rows`, `_write`, `_insert`, `_many`,
`_transaction`) and the two statements that read inside the stored JSON
(`FRAME_STATS`, `REMOVED_LABELS`), whose functions differ.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import re
import time
from collections.abc import Iterable, Mapping, Sequence
from contextlib import AbstractContextManager
from typing import Any

import numpy as np
from numpy.typing import NDArray

from graph.trajectory import PoseRow
from service.store import FrameFigures, KeyRecord, MapRecord, StoredFrame

Args = Mapping[str, Any]

_FRAME = "SELECT id, robot, seq, body, result, attempts FROM frames"
_POSE_COLUMNS = ("robot", "seq", "stamp", "x", "y", "theta")
_PRUNE_SNAPSHOTS = (
    "DELETE FROM snapshots WHERE {m}id NOT IN "
    "(SELECT id FROM snapshots{only} ORDER BY id DESC LIMIT :keep)"
)
_PRUNE_FRONTEND_STATES = (
    "DELETE FROM frontend_states WHERE {m}snapshot_id NOT IN (SELECT id FROM snapshots{only})"
)
_PRUNE_IMAGES = (
    "DELETE FROM images WHERE {m}frame_id <= (SELECT min(upto) FROM snapshots{only}) "
    "AND frame_id IN (SELECT frame_id FROM image_observations{only})"
)
"""Images of frames every kept snapshot covers whose observations are stored (what a
replay of such a frame, or an export, uses instead of the image)."""
_EVENTS_AFTER = "SELECT id, kind, data FROM events WHERE {m}id > :after ORDER BY id LIMIT :limit"
_LATEST_EVENT = "SELECT max(id) FROM events{only}"
_RECORD = "SELECT id, name, mode, config, created FROM maps"
_KEY = "SELECT id, map_id, scope, hash, created FROM keys"


def _record(row: Sequence[Any]) -> MapRecord:
    return MapRecord(row[0], row[1], row[2], json.loads(row[3]), row[4])


class _Database:
    """What a backend's connection gives: reads, and single committed writes."""

    def _rows(self, sql: str, args: Args) -> list[Any]:
        raise NotImplementedError

    def _write(self, sql: str, args: Args) -> None:
        """One statement, committed on its own."""
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class Catalog(_Database):
    """The list of maps, table ``maps``, and their API keys, table ``keys`` (written by the
    API processes); a backend gives `_rows`, `_write`, `remove` (atomic its own way) and
    `close`."""

    def add(self, record: MapRecord) -> None:
        self._write(
            "INSERT INTO maps (id, name, mode, config, created) "
            "VALUES (:id, :name, :mode, :config, :created)",
            {**record.as_dict(), "config": json.dumps(record.config)},
        )

    def remove(self, map_id: str) -> None:
        """Delete a map's record and its keys (one transaction)."""
        raise NotImplementedError

    def set_mode(self, map_id: str, mode: str) -> None:
        self._write("UPDATE maps SET mode = :mode WHERE id = :id", {"mode": mode, "id": map_id})

    def all(self) -> list[MapRecord]:
        """Every map, oldest first."""
        return [_record(r) for r in self._rows(f"{_RECORD} ORDER BY created, id", {})]

    def get(self, map_id: str) -> MapRecord | None:
        rows = self._rows(f"{_RECORD} WHERE id = :id", {"id": map_id})
        return _record(rows[0]) if rows else None

    def add_key(self, key: KeyRecord) -> None:
        self._write(
            "INSERT INTO keys (id, map_id, scope, hash, created) "
            "VALUES (:id, :map_id, :scope, :hash, :created)",
            dataclasses.asdict(key),
        )

    def remove_key(self, key_id: str) -> None:
        self._write("DELETE FROM keys WHERE id = :id", {"id": key_id})

    def keys(self) -> list[KeyRecord]:
        """Every API key (hashed), oldest first."""
        return [KeyRecord(*r) for r in self._rows(f"{_KEY} ORDER BY created, id", {})]


@functools.cache
def render(template: str, table: str = "", *, scoped: bool, meta: str) -> str:
    """A statement of this module for a backend (see the fields in the module's doc)."""
    return template.format(
        m="map_id = :m AND " if scoped else "",
        only=" WHERE map_id = :m" if scoped else "",
        mc="map_id, " if scoped else "",
        mv=":m, " if scoped else "",
        idc="id, " if scoped else "",
        idv=f"(SELECT coalesce(max(id), 0) + 1 FROM {table} WHERE map_id = :m), " if scoped else "",
        meta=meta,
    )


_NAMED = re.compile(r"(?<![:\w]):(\w+)")


@functools.cache
def pyformat(sql: str) -> str:
    """`sql` with its ``:name`` parameters written ``%(name)s`` (psycopg's style)."""
    return _NAMED.sub(r"%(\1)s", sql)


class MapStore(_Database):
    """One map's store (written only by the process that owns the map)."""

    SCOPED = True
    """Rows carry a ``map_id`` (PostgreSQL); False: the database is the map's (SQLite)."""
    META = "meta"
    NO_LIMIT: int | None = -1
    """The LIMIT that means none."""
    FRAME_STATS = ""
    """Figures of every processed frame from its stored result, in log order: (id, robot,
    seq, live, added, marginalised, total ms, covariance), as FrameFigures.from_row reads
    them."""
    REMOVED_LABELS = ""
    """(landmark id, label) of every landmark in the removal log."""

    map_id = ""

    # ------------------------------------------------------------ the backend's primitives
    def _insert(self, sql: str, args: Args) -> int:
        """An INSERT inside a transaction; the new row's id."""
        raise NotImplementedError

    def _many(self, sql: str, rows: Sequence[Args]) -> None:
        """One statement for each of `rows`, inside a transaction."""
        raise NotImplementedError

    def _transaction(self) -> AbstractContextManager[Any]:
        raise NotImplementedError

    def checkpoint(self) -> None:
        """Make the store's size on disk say what it holds (SQLite: fold the WAL)."""
        raise NotImplementedError

    # ------------------------------------------------------------ writing the SQL
    def _sql(self, template: str, table: str = "") -> str:
        return render(template, table, scoped=self.SCOPED, meta=self.META)

    def _args(self, **args: Any) -> dict[str, Any]:
        return {"m": self.map_id, **args}

    def _do(self, template: str, **args: Any) -> None:
        """One statement inside the current transaction."""
        self._many(self._sql(template), [self._args(**args)])

    def _each(self, template: str, rows: Iterable[Mapping[str, Any]]) -> None:
        """One statement for each of `rows` inside the current transaction."""
        self._many(self._sql(template), [self._args(**r) for r in rows])

    def _commit(self, template: str, **args: Any) -> None:
        """One statement, committed on its own."""
        self._write(self._sql(template), self._args(**args))

    def _new_row(self, template: str, table: str, **args: Any) -> int:
        """An INSERT inside the current transaction; the new row's id."""
        return self._insert(self._sql(template, table), self._args(**args))

    def _get(self, template: str, **args: Any) -> list[Any]:
        return self._rows(self._sql(template), self._args(**args))

    def _one(self, template: str, **args: Any) -> Any:
        rows = self._get(template, **args)
        return rows[0][0] if rows else None

    def _count(self, table: str) -> int:
        return int(self._one(f"SELECT count(*) FROM {table}{{only}}"))

    # ------------------------------------------------------------ meta
    def get_meta(self, key: str) -> Any | None:
        value = self._one("SELECT value FROM {meta} WHERE {m}key = :key", key=key)
        return None if value is None else json.loads(value)

    def set_meta(self, key: str, value: Any) -> None:
        self._commit(
            "INSERT INTO {meta} ({mc}key, value) VALUES ({mv}:key, :value) "
            "ON CONFLICT ({mc}key) DO UPDATE SET value = excluded.value",
            key=key,
            value=json.dumps(value),
        )

    # ------------------------------------------------------------ the frame log
    def find_frame(self, robot: str, seq: int) -> StoredFrame | None:
        rows = self._get(f"{_FRAME} WHERE {{m}}robot = :robot AND seq = :seq", robot=robot, seq=seq)
        return StoredFrame(*rows[0]) if rows else None

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
        with self._transaction():
            frame_id = self._new_row(
                "INSERT INTO frames ({mc}{idc}robot, seq, body, received) "
                "VALUES ({mv}{idv}:robot, :seq, :body, :received)",
                "frames",
                robot=robot,
                seq=seq,
                body=body,
                received=time.time(),
            )
            if image is not None:
                self._do(
                    "INSERT INTO images ({mc}frame_id, data) VALUES ({mv}:id, :data)",
                    id=frame_id,
                    data=image,
                )
            if observations is not None:
                self._do(
                    "INSERT INTO image_observations ({mc}frame_id, observations) "
                    "VALUES ({mv}:id, :observations)",
                    id=frame_id,
                    observations=observations,
                )
        return frame_id

    def frame_image(self, frame_id: int) -> bytes | None:
        """The encoded image of a logged image frame (None for a frame without one)."""
        data = self._one("SELECT data FROM images WHERE {m}frame_id = :id", id=frame_id)
        return None if data is None else bytes(data)

    def image_observations(self, frame_id: int) -> list[Any] | None:
        """The labelled observations a logged image frame's image gave (None: not stored)."""
        text = self._one(
            "SELECT observations FROM image_observations WHERE {m}frame_id = :id", id=frame_id
        )
        return None if text is None else list(json.loads(text))

    def count_attempt(self, frame_id: int) -> None:
        """Note (durably) that an unfinished frame is about to be processed again."""
        self._commit("UPDATE frames SET attempts = attempts + 1 WHERE {m}id = :id", id=frame_id)

    def delete_frame(self, frame_id: int) -> None:
        with self._transaction():
            self._do("DELETE FROM frames WHERE {m}id = :id", id=frame_id)
            for table in ("images", "image_observations"):
                self._do(f"DELETE FROM {table} WHERE {{m}}frame_id = :id", id=frame_id)

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
        """Store a frame's result, its events and removals (landmark id, frame, record
        JSON), the trajectory rows it made final (and, for an image frame, the observations
        its image gave, JSON text) in one transaction; event ids. `restored`: landmark ids
        that left the archive in the frame; `archived`: (landmark id, frame, record JSON)
        of those that entered it (after `restored`: a landmark may do both)."""
        now = time.time()
        with self._transaction():
            self._do(
                "UPDATE frames SET result = :result WHERE {m}id = :id", result=result, id=frame_id
            )
            if observations is not None:
                self._do(
                    "INSERT INTO image_observations ({mc}frame_id, observations) "
                    "VALUES ({mv}:id, :observations) ON CONFLICT ({mc}frame_id) "
                    "DO UPDATE SET observations = excluded.observations",
                    id=frame_id,
                    observations=observations,
                )
            if removals:
                self._each(
                    "INSERT INTO removal_log ({mc}landmark_id, frame, record) "
                    "VALUES ({mv}:lid, :frame, :record) ON CONFLICT DO NOTHING",
                    [{"lid": lid, "frame": f, "record": rec} for lid, f, rec in removals],
                )
            if restored:
                rows = [{"lid": lid} for lid in restored]
                self._each("DELETE FROM archive WHERE {m}landmark_id = :lid", rows)
            if archived:
                self._each(
                    "INSERT INTO archive ({mc}landmark_id, frame, record) "
                    "VALUES ({mv}:lid, :frame, :record) ON CONFLICT ({mc}landmark_id) "
                    "DO UPDATE SET frame = excluded.frame, record = excluded.record",
                    [{"lid": lid, "frame": f, "record": rec} for lid, f, rec in archived],
                )
            if poses:
                self._put_poses(poses)
            return [self._insert_event(kind, data, now) for kind, data in events]

    def _insert_event(self, kind: str, data: str, now: float) -> int:
        return self._new_row(
            "INSERT INTO events ({mc}{idc}kind, data, created) "
            "VALUES ({mv}{idv}:kind, :data, :created)",
            "events",
            kind=kind,
            data=data,
            created=now,
        )

    def frames_after(self, frame_id: int) -> list[StoredFrame]:
        """Logged frames with id > `frame_id`, in log order."""
        rows = self._get(f"{_FRAME} WHERE {{m}}id > :id ORDER BY id", id=frame_id)
        return [StoredFrame(*r) for r in rows]

    def frame_count(self) -> int:
        return self._count("frames")

    def frame_stats(self) -> list[FrameFigures]:
        """Figures of every processed frame from its stored result, in log order (the
        covariance is left as JSON text)."""
        return [FrameFigures.from_row(tuple(r)) for r in self._get(self.FRAME_STATS)]

    # ------------------------------------------------------------ final trajectory rows
    def _put_poses(self, rows: list[PoseRow]) -> None:
        self._each(
            "INSERT INTO poses ({mc}robot, seq, stamp, x, y, theta) "
            "VALUES ({mv}:robot, :seq, :stamp, :x, :y, :theta) "
            "ON CONFLICT ({mc}robot, seq) DO UPDATE SET stamp = excluded.stamp, "
            "x = excluded.x, y = excluded.y, theta = excluded.theta",
            [{f: getattr(r, f) for f in _POSE_COLUMNS} for r in rows],
        )

    def put_poses(self, rows: list[PoseRow]) -> None:
        """Store final trajectory rows (replacing those of the same robot and seq)."""
        if rows:
            with self._transaction():
                self._put_poses(rows)

    def poses(self, robot: str | None = None) -> dict[str, NDArray[np.float64]]:
        """Stored final rows per robot (`robot`: that one only), each an (N, 5) array
        seq, stamp, x, y, theta sorted by seq (as BearingSlam.trajectory)."""
        return _pose_arrays(self._get(_poses_sql(robot), robot=robot))

    def pose_positions(self) -> NDArray[np.float64]:
        """(N, 2) x, y of every stored final row, metres."""
        rows = self._get("SELECT x, y FROM poses{only}")
        return np.array(rows, dtype=np.float64).reshape(-1, 2)

    def pose_count(self) -> int:
        return self._count("poses")

    # ------------------------------------------------------------ snapshots
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
        an export, uses instead of the image)."""
        with self._transaction():
            snapshot_id = self._new_row(
                "INSERT INTO snapshots ({mc}{idc}upto, created, state) "
                "VALUES ({mv}{idv}:upto, :created, :state)",
                "snapshots",
                upto=upto,
                created=time.time(),
                state=state,
            )
            if frontend is not None:
                self._do(
                    "INSERT INTO frontend_states ({mc}snapshot_id, state) VALUES ({mv}:id, :state)",
                    id=snapshot_id,
                    state=frontend,
                )
            prune = [_PRUNE_SNAPSHOTS, _PRUNE_FRONTEND_STATES]
            for template in [*prune, _PRUNE_IMAGES] if prune_images else prune:
                self._do(template, keep=keep)

    def image_count(self) -> int:
        """Images stored in the log."""
        return self._count("images")

    def latest_snapshot(self) -> tuple[int, bytes] | None:
        """(log id it covers, state) of the newest snapshot."""
        rows = self._get("SELECT upto, state FROM snapshots{only} ORDER BY id DESC LIMIT 1")
        return (int(rows[0][0]), bytes(rows[0][1])) if rows else None

    def latest_frontend_state(self) -> bytes | None:
        """The front end's state stored with the latest snapshot (None if it has none)."""
        state = self._one(
            "SELECT state FROM frontend_states WHERE {m}snapshot_id = "
            "(SELECT max(id) FROM snapshots{only})"
        )
        return None if state is None else bytes(state)

    # ------------------------------------------------------------ removals and events
    def removals(self, limit: int | None = None) -> list[dict[str, Any]]:
        """The most recent `limit` removals (all if None), oldest first."""
        rows = self._get(
            "SELECT record FROM (SELECT frame, landmark_id, record FROM removal_log{only} "
            "ORDER BY frame DESC, landmark_id DESC LIMIT :limit) r ORDER BY frame, landmark_id",
            limit=self.NO_LIMIT if limit is None else limit,
        )
        return [json.loads(r[0]) for r in rows]

    def removed_labels(self) -> dict[int, str]:
        """Label of every landmark in the removal log, by landmark id."""
        return {int(i): str(label) for i, label in self._get(self.REMOVED_LABELS)}

    def removal_count(self) -> int:
        """Removals in the log (a landmark removed twice counts twice)."""
        return self._count("removal_log")

    def archived(self) -> list[dict[str, Any]]:
        """The archived landmarks (graph.archive documents), by landmark id."""
        rows = self._get("SELECT record FROM archive{only} ORDER BY landmark_id")
        return [json.loads(r[0]) for r in rows]

    def prune_events(self, keep: int) -> None:
        """Delete all but the newest `keep` events."""
        self._commit(
            "DELETE FROM events WHERE {m}id <= (SELECT max(id) FROM events{only}) - :keep",
            keep=keep,
        )


class MapReads:
    """A store's reads of one map for the API process (events, final trajectory rows); a
    backend gives `_read` (and `SCOPED`, as `MapStore`)."""

    SCOPED = True

    def _read(self, map_id: str, sql: str, args: Args) -> list[Any]:
        """The rows of one statement of this module on `map_id`'s rows, read only."""
        raise NotImplementedError

    def _rows_of(self, map_id: str, template: str, **args: Any) -> list[Any]:
        sql = render(template, scoped=self.SCOPED, meta="")
        return self._read(map_id, sql, {"m": map_id, **args})

    def read_events(self, map_id: str, after: int, limit: int = 500) -> list[tuple[int, str, str]]:
        """Events with id > `after` of a map: (id, kind, data JSON), oldest first."""
        rows = self._rows_of(map_id, _EVENTS_AFTER, after=after, limit=limit)
        return [(int(r[0]), str(r[1]), str(r[2])) for r in rows]

    def latest_event_id(self, map_id: str) -> int:
        """The id of a map's newest event (0 if none)."""
        rows = self._rows_of(map_id, _LATEST_EVENT)
        return int(rows[0][0] or 0) if rows else 0

    def read_poses(self, map_id: str, robot: str | None = None) -> dict[str, Any]:
        """A map's final trajectory rows per robot (see MapStore.poses)."""
        return _pose_arrays(self._rows_of(map_id, _poses_sql(robot), robot=robot))


def _poses_sql(robot: str | None) -> str:
    which = "{only}" if robot is None else " WHERE {m}robot = :robot"
    return f"SELECT robot, seq, stamp, x, y, theta FROM poses{which} ORDER BY robot, seq"


def _pose_arrays(rows: Iterable[Sequence[Any]]) -> dict[str, NDArray[np.float64]]:
    """Stored trajectory rows (robot, seq, stamp, x, y, theta; sorted by robot and seq)
    per robot as (N, 5) arrays seq, stamp, x, y, theta."""
    out: dict[str, list[tuple[float, ...]]] = {}
    for name, *values in rows:
        out.setdefault(str(name), []).append(tuple(values))
    return {k: np.array(v, dtype=np.float64).reshape(-1, 5) for k, v in out.items()}
