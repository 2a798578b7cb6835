"""The service as the API sees it: one method per use case, routed to workers.

`MapService` lives in the API process. It keeps the catalogue of maps (the store's),
the engine that runs the maps (local worker processes, or Ray actors), each map's
latest published view (service.published: reads are answered from it, never queued
behind frames), and each map's event feed (service.events), which the frame answers
fill and the event streams read from memory. Everything heavy happens in the workers.
"""

from __future__ import annotations

import asyncio
import builtins
import dataclasses
import logging
import math
import secrets
import time
from collections.abc import Callable
from typing import Any, TypeVar

from service.engine import Engine
from service.errors import ServiceError, unknown_map
from service.events import EventRows, Notifier, sse_bytes
from service.exchange import Export
from service.frame_results import FrameReply
from service.keys import key_hash, new_key, new_key_id, same_hash
from service.pipeline.config import MapConfig, Mode, slam_config
from service.pool import WorkerPool
from service.published import MapView, ViewDelta
from service.queries import Landmarks, SetMode, Summary, Trajectory
from service.requests import (
    CreateMap,
    DeleteMap,
    ImportMap,
    MapRequest,
    RefreshView,
    SubmitFrame,
)
from service.settings import Settings
from service.store import KeyRecord, MapRecord

log = logging.getLogger(__name__)

T = TypeVar("T")


def make_engine(settings: Settings, *, on_restart: Callable[[int], None] | None = None) -> Engine:
    """The engine `settings.engine` names."""
    if settings.engine == "ray":
        from service.ray_engine import RayEngine

        return RayEngine(settings, on_restart=on_restart)
    return WorkerPool(settings, on_restart=on_restart)


class MapService:
    """Maps: create, list, delete, frames, queries, export/import."""

    def __init__(self, settings: Settings, *, on_worker_restart: Any = None) -> None:
        self.settings = settings
        self.store = settings.open_store()
        self._catalog = self.store.catalog()
        self._records: dict[str, MapRecord] = {r.id: r for r in self._catalog.all()}
        self._keys: dict[str, KeyRecord] = {k.hash: k for k in self._catalog.keys()}
        self._creating = 0
        self.pool: Engine = make_engine(settings, on_restart=on_worker_restart)
        self.pool.on_view = self._publish_view
        self._views: dict[str, MapView] = {}
        self._new_ids: set[str] = set()
        self._refreshing: set[tuple[str, bool]] = set()
        self._refreshed: dict[str, float] = {}
        """When each map's landmarks and rows were last asked for (monotonic s)."""
        self._tasks: set[asyncio.Task[None]] = set()
        """Maps being created or imported (their first view comes before their record)."""
        self.notifier = Notifier()
        self.started = False

    def _publish_view(self, delta: ViewDelta) -> None:
        """A map's new view from its worker (a delta from the view it sent before)."""
        map_id = delta.map_id
        if map_id not in self._records and map_id not in self._new_ids:
            return
        view = delta.apply(self._views.get(map_id))
        if view is not None:
            self._views[map_id] = view
            return
        # Not made from the view held here (a view was lost): the worker answers the
        # map's reads until the whole view it is asked for arrives.
        self._views.pop(map_id, None)
        self._refresh(map_id, whole=True)

    async def start(self) -> None:
        await self.pool.start(self._records)
        self.started = True

    async def stop(self) -> None:
        for task in self._tasks:
            task.cancel()
        await self.pool.stop()
        self._catalog.close()
        self.store.close()

    @property
    def ready(self) -> bool:
        return self.started and self.pool.ready

    @property
    def _long_timeout_s(self) -> float:
        """An export's or import's time limit (a large map takes a while)."""
        return max(self.settings.workers.request_timeout_s, 600.0)

    # ------------------------------------------------------------ maps
    def record(self, map_id: str) -> MapRecord:
        record = self._records.get(map_id)
        if record is None and self.pool.shared:
            # another API process of the same cluster may have created it
            record = self._catalog.get(map_id)
            if record is not None:
                self._records[map_id] = record
                self.pool.track(map_id)
        if record is None:
            raise unknown_map(map_id)
        return record

    def list(self) -> list[MapRecord]:
        if self.pool.shared:
            self._records = {r.id: r for r in self._catalog.all()}
        return list(self._records.values())

    def _new_id(self) -> str:
        while True:
            map_id = secrets.token_hex(6)
            if map_id not in self._records:
                return map_id

    def _new_record(self, name: str, config: MapConfig, mode: Mode) -> MapRecord:
        config = config.for_new_map(
            self.settings.default_landmark_cap, self.settings.default_camera_landmark_cap
        )
        record = MapRecord(self._new_id(), name, mode, config.model_dump(mode="json"), time.time())
        try:
            slam_config(record.config, mode)
        except ValueError as exc:
            raise ServiceError(422, "invalid-config", "Invalid map config", str(exc)) from exc
        return record

    def _check_room(self) -> None:
        limit = self.settings.max_maps
        if len(self.list()) + self._creating >= limit:
            raise ServiceError(
                507,
                "too-many-maps",
                "Too many maps",
                f"the service holds its limit of {limit} maps (setting max_maps); "
                "delete a map first",
            )

    async def _new_map(
        self, map_id: str, request: CreateMap | ImportMap, record_of: Callable[[Any], MapRecord]
    ) -> Any:
        """The worker's reply to a create or import, the map in the catalogue. On any
        failure (the worker's, or the catalogue's: a full disk) the worker is told to
        remove whatever it wrote for `map_id`, so no orphan file stays behind.
        `record_of(reply)` is the new map's MapRecord."""
        self._check_room()
        self._creating += 1
        self._new_ids.add(map_id)
        try:
            timeout = None if isinstance(request, CreateMap) else self._long_timeout_s
            reply = await self.pool.call(map_id, request, timeout_s=timeout)
            record: MapRecord = record_of(reply)
            self._catalog.add(record)
        except Exception:
            try:
                await self.pool.call(map_id, DeleteMap())
            except Exception:
                log.exception("could not remove the files of the failed new map %s", map_id)
            self.pool.untrack(map_id)
            self._views.pop(map_id, None)
            raise
        finally:
            self._creating -= 1
            self._new_ids.discard(map_id)
        self._records[record.id] = record
        self.pool.track(record.id)
        return reply

    async def create(self, *, name: str, config: MapConfig, mode: Mode) -> dict[str, Any]:
        record = self._new_record(name, config, mode)
        request = CreateMap(record.as_dict())
        summary = await self._new_map(record.id, request, lambda _: record)
        return {**summary, "worker": self.pool.worker_of(record.id)}

    async def summary(self, map_id: str) -> dict[str, Any]:
        summary = await self.query(map_id, Summary())
        return {**summary, "worker": self.pool.worker_of(map_id)}

    async def delete(self, map_id: str) -> None:
        self.record(map_id)
        self._catalog.remove(map_id)  # and its keys
        del self._records[map_id]
        self._keys = {h: k for h, k in self._keys.items() if k.map_id != map_id}
        self._views.pop(map_id, None)
        self._refreshed.pop(map_id, None)
        self.notifier.forget(map_id)
        try:  # on the worker that has the map open
            await self.pool.call(map_id, DeleteMap())
        finally:
            self.pool.untrack(map_id)

    async def set_mode(self, map_id: str, mode: Mode) -> dict[str, Any]:
        record = self.record(map_id)
        summary = await self.pool.call(map_id, SetMode(mode))
        self._catalog.set_mode(map_id, mode)
        self._records[map_id] = dataclasses.replace(record, mode=mode)
        return {**summary, "worker": self.pool.worker_of(map_id)}

    # ------------------------------------------------------------ frames and queries
    async def submit(
        self, map_id: str, frame: dict[str, Any], image: bytes | None = None
    ) -> FrameReply:
        """One frame to its map; the worker's reply (result, replayed, event ids, ...).

        With `image`, `frame` is the meta of an image frame (PNG/JPEG bytes, decoded by
        the map's worker)."""
        self.record(map_id)
        reply = await self.pool.call(map_id, SubmitFrame(frame, image))
        if reply.events:
            if self.pool.shared:  # other API processes feed the store too: read it
                self.notifier.notify(map_id)
            else:
                self.notifier.publish(map_id, reply.events)
        return reply

    async def query(self, map_id: str, request: MapRequest[T]) -> T:
        """A query (service.queries) on a map; its answer: from the map's published view
        when the query can be answered from it (no wait for the worker; a part of the
        view that lags behind the map only while the worker is busy), else the
        worker's."""
        self.record(map_id)
        view = self._views.get(map_id)
        behind = view is not None and request.view_behind(view)
        if view is not None and not (behind and not self.pool.busy(map_id)):
            if request.view_reads_store:
                answer = await asyncio.to_thread(request.from_view, view, self.store)
            else:
                answer = request.from_view(view, self.store)
            if answer is not None:
                if behind and isinstance(request, Landmarks | Trajectory):
                    self._refresh(map_id)
                return answer
        return await self.pool.call(map_id, request)

    def _refresh(self, map_id: str, *, whole: bool = False) -> None:
        """Ask the map's worker for its live landmarks and held trajectory rows now (one
        request at a time, and at most once per `api.view_refresh_s`; `whole`: all of its
        view, at once); the view it publishes answers the next reads."""
        key = (map_id, whole)
        if key in self._refreshing:
            return
        if not whole:
            now = time.monotonic()
            if now - self._refreshed.get(map_id, -math.inf) < self.settings.api.view_refresh_s:
                return
            self._refreshed[map_id] = now
        self._refreshing.add(key)

        async def refresh() -> None:
            try:
                await self.pool.call(map_id, RefreshView(whole))
            except Exception:
                log.warning("refreshing the view of map %s failed", map_id, exc_info=True)
            finally:
                self._refreshing.discard(key)

        task = asyncio.get_running_loop().create_task(refresh())
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def read_events(self, map_id: str, after: int) -> EventRows:
        """Stored events of a map after id `after`: (id, kind, data JSON) (blocking I/O)."""
        return self.store.read_events(map_id, after)

    async def events_after(self, map_id: str, after: int) -> tuple[int, bytes]:
        """A map's events after id `after` as server-sent events: (the last id, bytes;
        (`after`, b"") when there are none). From the map's feed in memory, or (a stream
        that starts or fell behind) from the store."""
        fed = self.notifier.fed_sse(map_id, after)
        if fed is not None:
            return fed
        rows = await asyncio.to_thread(self.read_events, map_id, after)
        return (rows[-1][0], sse_bytes(rows)) if rows else (after, b"")

    def exists(self, map_id: str) -> bool:
        """The map is in the catalogue (with a shared engine: read again)."""
        if self.pool.shared:
            return map_id in {r.id for r in self.list()}
        return map_id in self._records

    def latest_event_id(self, map_id: str) -> int:
        """The id of the map's newest stored event, 0 if none (blocking I/O)."""
        self.record(map_id)
        return self.store.latest_event_id(map_id)

    # ------------------------------------------------------------ export / import
    async def export(self, map_id: str) -> bytes:
        """The map's export document as JSON bytes (serialised in the worker)."""
        self.record(map_id)
        return await self.pool.call(map_id, Export(), timeout_s=self._long_timeout_s)

    async def import_map(self, body: bytes) -> dict[str, Any]:
        """A new map from an export document (bytes; parsed, checked and replayed by the
        worker that will own the new map, so a large document never blocks the API)."""
        map_id = self._new_id()
        request = ImportMap(body, time.time(), self.settings.default_landmark_cap)
        reply = await self._new_map(map_id, request, lambda r: MapRecord.from_dict(r["record"]))
        return {**reply["summary"], "worker": self.pool.worker_of(map_id)}

    # ------------------------------------------------------------ API keys
    def create_key(self, map_id: str, scope: str) -> tuple[KeyRecord, str]:
        """A new key of `scope` for the map: its record and the secret (shown only now)."""
        self.record(map_id)
        secret = new_key()
        key = KeyRecord(new_key_id(), map_id, scope, key_hash(secret), time.time())
        self._catalog.add_key(key)
        self._keys[key.hash] = key
        return key, secret

    def _current_keys(self) -> dict[str, KeyRecord]:
        """The keys by hash. With a shared engine they are read from the catalogue again:
        another API process may have created or revoked one."""
        if self.pool.shared:
            self._keys = {k.hash: k for k in self._catalog.keys()}
        return self._keys

    def keys(self, map_id: str) -> builtins.list[KeyRecord]:
        self.record(map_id)
        return sorted(
            (k for k in self._current_keys().values() if k.map_id == map_id),
            key=lambda k: k.created,
        )

    def delete_key(self, map_id: str, key_id: str) -> None:
        for key in self.keys(map_id):
            if key.id == key_id:
                self._catalog.remove_key(key_id)
                self._keys.pop(key.hash, None)
                self.notifier.notify(map_id)  # its open event streams end now
                return
        raise ServiceError(
            404, "unknown-key", "Unknown key", f"map {map_id!r} has no key with id {key_id!r}"
        )

    def key_alive(self, key: KeyRecord) -> bool:
        """Whether `key` is still valid (not revoked, its map not deleted)."""
        return self._current_keys().get(key.hash) == key

    def find_key(self, secret: str) -> KeyRecord | None:
        """The stored key whose hash is the secret's, or None."""
        digest = key_hash(secret)
        key = self._current_keys().get(digest)
        return key if key is not None and same_hash(key.hash, digest) else None
