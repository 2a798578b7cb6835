"""The store: a catalogue of maps, and per map its durable frame log and derived state.

The records of this module, the interface of a map's store and of the catalogue written
once with their SQL (service.store_sql: `MapStore`, `Catalog`), and two backends with the
same schema and the same semantics:

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
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from service.store_sql import Catalog, MapStore

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
        return {name: getattr(self, name) for name in self.__slots__}

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
    """A whole store: the catalogue, each map's place, and the API process's reads of a
    map (events, final trajectory rows: service.store_sql.MapReads)."""

    description: str
    """Where the store is, for logs (no password)."""

    def catalog(self) -> Catalog: ...
    def place(self, map_id: str) -> MapPlace: ...
    def read_events(
        self, map_id: str, after: int, limit: int = 500
    ) -> list[tuple[int, str, str]]: ...
    def latest_event_id(self, map_id: str) -> int: ...
    def read_poses(self, map_id: str, robot: str | None = None) -> dict[str, Any]: ...
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
