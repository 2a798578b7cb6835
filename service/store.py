"""The store: a catalogue of maps, and per map its durable frame log and derived state.

One interface, two implementations with the same schema and the same semantics:

- ``service.store_sqlite``: embedded SQLite, a catalogue file and one database file
  per map under a directory (the default; one machine);
- ``service.store_pg``: PostgreSQL (psycopg 3), every map in one database, rows
  keyed by map id (maps served from several machines).

What a map's store keeps: the frame log (a frame is appended and committed before
it is processed; ``(robot, seq)`` is unique, which backs idempotent retries), each
frame's result with its events and the removals it caused (one transaction), the
trajectory rows the estimator made final, snapshots of the estimator (bytes) with the
front end's state, a camera map's images and the observations they gave, and a few
meta values. Log ids, snapshot ids and event ids count from 1 per map and only grow.

The removal log (``removal_log``, one row per removal, keyed by (frame, landmark id): a
landmark restored from the archive may be removed again; a SQLite file's older
``removals`` table, one row per landmark, is moved into it when the map's file is
opened) and the archive of removed landmarks (``archive``, graph.archive: one row per
landmark that is not live, its last estimate, covariance, E(X), count; a restored
landmark's row is deleted) are written with the frame that removed or restored them.

`open_store(url, ...)` picks the implementation: a ``postgresql://`` URL, or a
directory for SQLite.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from graph.trajectory import PoseRow

POSTGRES_SCHEMES = ("postgresql://", "postgres://")


def is_postgres_url(url: str | None) -> bool:
    return url is not None and url.startswith(POSTGRES_SCHEMES)


# --------------------------------------------------------------------------- records


@dataclass(frozen=True, slots=True)
class MapRecord:
    """A map as the catalogue knows it. `config` is the API's map config (JSON object)."""

    id: str
    name: str
    mode: str
    config: dict[str, Any]
    created: float

    def as_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "name": self.name,
            "mode": self.mode,
            "config": self.config,
            "created": self.created,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> MapRecord:
        return cls(d["id"], d["name"], d["mode"], dict(d["config"]), float(d["created"]))


@dataclass(frozen=True, slots=True)
class KeyRecord:
    """A map's API key as stored: its sha256 `hash` (hex), never the key itself."""

    id: str
    map_id: str
    scope: str
    hash: str
    created: float


@dataclass(frozen=True, slots=True)
class FrameFigures:
    """What one frame's stored result reported (see `MapStore.frame_stats`)."""

    frame_id: int
    robot: str
    seq: int
    live: int
    """live landmarks after the frame"""
    added: tuple[int, ...]
    """landmark ids the frame initialised that were still live after it"""
    marginalised: tuple[int, ...]
    """landmark ids the budget removed after the frame"""
    total_ms: float | None
    """the estimator's time for the frame (timing_ms.total), milliseconds"""
    covariance_json: str | None
    """the 3x3 pose covariance as JSON text, or None"""

    @classmethod
    def from_row(cls, row: tuple[Any, ...]) -> FrameFigures:
        """From (id, robot, seq, live, added JSON, marginalised JSON, total ms, covariance
        JSON) as a store's query picked them out of a result; JSON null counts as absent."""
        i, robot, seq, *values = row
        live, added, marg, total, cov = (None if v == "null" else v for v in values)
        return cls(
            int(i),
            str(robot),
            int(seq),
            int(live or 0),
            tuple(json.loads(added or "[]")),
            tuple(json.loads(marg or "[]")),
            None if total is None else float(total),
            cov,
        )


@dataclass(frozen=True, slots=True)
class StoredFrame:
    id: int
    robot: str
    seq: int
    body: str
    result: str | None
    attempts: int = 0


# --------------------------------------------------------------------------- interfaces


class Catalog(Protocol):
    """The list of maps and their API keys (written by the API processes)."""

    def add(self, record: MapRecord) -> None: ...
    def remove(self, map_id: str) -> None:
        """Delete a map's record and its keys (one transaction)."""
        ...

    def set_mode(self, map_id: str, mode: str) -> None: ...
    def all(self) -> list[MapRecord]:
        """Every map, oldest first."""
        ...

    def get(self, map_id: str) -> MapRecord | None: ...
    def add_key(self, key: KeyRecord) -> None: ...
    def remove_key(self, key_id: str) -> None: ...
    def keys(self) -> list[KeyRecord]:
        """Every API key (hashed), oldest first."""
        ...

    def close(self) -> None: ...


class MapStore(Protocol):
    """One map's store (written only by the process that owns the map)."""

    def close(self) -> None: ...

    # meta
    def get_meta(self, key: str) -> Any | None: ...
    def set_meta(self, key: str, value: Any) -> None: ...

    # the frame log
    def find_frame(self, robot: str, seq: int) -> StoredFrame | None: ...
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
        ...

    def frame_image(self, frame_id: int) -> bytes | None:
        """The encoded image of a logged image frame (None for a frame without one)."""
        ...

    def image_observations(self, frame_id: int) -> list[Any] | None:
        """The labelled observations a logged image frame's image gave (None: not stored)."""
        ...

    def count_attempt(self, frame_id: int) -> None:
        """Note (durably) that an unfinished frame is about to be processed again."""
        ...

    def delete_frame(self, frame_id: int) -> None: ...
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
        ...

    def add_event(self, kind: str, data: str) -> int: ...
    def frames_after(self, frame_id: int) -> list[StoredFrame]:
        """Logged frames with id > `frame_id`, in log order."""
        ...

    def frame_count(self) -> int: ...
    def frame_stats(self) -> list[FrameFigures]:
        """Figures of every processed frame from its stored result, in log order."""
        ...

    # final trajectory rows
    def put_poses(self, rows: list[PoseRow]) -> None:
        """Store final trajectory rows (replacing those of the same robot and seq)."""
        ...

    def poses(self, robot: str | None = None) -> dict[str, NDArray[np.float64]]:
        """Stored final rows per robot (`robot`: that one only), each an (N, 5) array
        seq, stamp, x, y, theta sorted by seq (as BearingSlam.trajectory)."""
        ...

    def pose_positions(self) -> NDArray[np.float64]:
        """(N, 2) x, y of every stored final row, metres."""
        ...

    def pose_count(self) -> int: ...

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
        an export, uses instead of the image)."""
        ...

    def checkpoint(self) -> None:
        """Make the store's size on disk say what it holds (SQLite: fold the WAL)."""
        ...

    def image_count(self) -> int:
        """Images stored in the log."""
        ...

    def latest_snapshot(self) -> tuple[int, bytes] | None:
        """(log id it covers, state) of the newest snapshot."""
        ...

    def latest_frontend_state(self) -> bytes | None:
        """The front end's state stored with the latest snapshot (None if it has none)."""
        ...

    # removals and events
    def removals(self, limit: int | None = None) -> list[dict[str, Any]]:
        """The most recent `limit` removals (all if None), oldest first."""
        ...

    def removed_labels(self) -> dict[int, str]:
        """Label of every landmark in the removal log, by landmark id."""
        ...

    def removal_count(self) -> int:
        """Removals in the log (a landmark removed twice counts twice)."""
        ...

    def archived(self) -> list[dict[str, Any]]:
        """The archived landmarks (graph.archive documents), by landmark id."""
        ...

    def prune_events(self, keep: int) -> None:
        """Delete all but the newest `keep` events."""
        ...


class MapPlace(Protocol):
    """Where one map's store lives (a file, or a map id in a database)."""

    map_id: str

    def exists(self) -> bool:
        """The map has a store here (created and not removed)."""
        ...

    def open(self) -> MapStore:
        """The map's store, its schema created if missing."""
        ...

    def remove(self) -> None:
        """Delete everything the map stored (nothing happens if there is nothing)."""
        ...


class Store(Protocol):
    """A whole store: the catalogue, each map's place, and event reads for the API."""

    description: str
    """Where the store is, for logs (no password)."""

    def catalog(self) -> Catalog: ...
    def place(self, map_id: str) -> MapPlace: ...
    def read_events(self, map_id: str, after: int, limit: int = 500) -> list[tuple[int, str, str]]:
        """Events with id > `after` of a map: (id, kind, data JSON), oldest first."""
        ...

    def latest_event_id(self, map_id: str) -> int:
        """The id of a map's newest event (0 if none)."""
        ...

    def close(self) -> None: ...


def open_store(url: str | None, *, data_dir: Path, synchronous: str) -> Store:
    """The store a URL names: ``postgresql://...`` (takes precedence over `data_dir`), a
    directory (SQLite), or None for SQLite in `data_dir`."""
    if is_postgres_url(url):
        from service.store_pg import PgStore

        assert url is not None
        return PgStore(url)
    from service.store_sqlite import SqliteStore

    return SqliteStore(Path(url) if url else data_dir, synchronous=synchronous)


def as_place(where: Path | MapPlace, *, synchronous: str) -> MapPlace:
    """A map place from a SQLite file path, or the place itself."""
    if isinstance(where, Path):
        from service.store_sqlite import SqliteMap

        return SqliteMap(where, synchronous=synchronous)
    return where


def connection_lost(exc: BaseException) -> bool:
    """The exception says the store's server went away (a PostgreSQL restart, the
    network): what was open on it must be reopened."""
    if type(exc).__module__.split(".")[0] != "psycopg":
        return False
    from service.store_pg import CONNECTION_ERRORS

    return isinstance(exc, CONNECTION_ERRORS)
