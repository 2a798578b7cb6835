"""The service as the API sees it: one method per use case, all routed to workers.

`MapService` lives in the API process. It keeps the catalogue of maps (the store's),
the engine that runs the maps (local worker processes, or Ray actors), and a notifier
that wakes the event streams of a map when its worker reported something new.
Everything heavy happens in the workers.
"""

from __future__ import annotations

import asyncio
import secrets
import time
from typing import Any

from service.errors import ServiceError, unknown_map
from service.mapconfig import MapConfig, Mode, slam_config
from service.pool import Engine, make_engine
from service.settings import Settings
from service.store import MapRecord

EventRows = list[tuple[int, str, str]]
"""Stored events: (id, kind, data JSON), oldest first."""


class Notifier:
    """Wakes the waiters of a map when new events were stored for it."""

    def __init__(self) -> None:
        self._events: dict[str, asyncio.Event] = {}

    def handle(self, map_id: str) -> asyncio.Event:
        """An event set at the next `notify(map_id)`; take it *before* reading the store."""
        return self._events.setdefault(map_id, asyncio.Event())

    def notify(self, map_id: str) -> None:
        event = self._events.pop(map_id, None)
        if event is not None:
            event.set()


class MapService:
    """Maps: create, list, delete, frames, queries, export/import."""

    def __init__(self, settings: Settings, *, on_worker_restart: Any = None) -> None:
        self.settings = settings
        self.store = settings.open_store()
        self._catalog = self.store.catalog()
        self._records: dict[str, MapRecord] = {r.id: r for r in self._catalog.all()}
        self.pool: Engine = make_engine(settings, on_restart=on_worker_restart)
        self.notifier = Notifier()
        self.started = False

    async def start(self) -> None:
        await self.pool.start(self._records)
        self.started = True

    async def stop(self) -> None:
        await self.pool.stop()
        self._catalog.close()
        self.store.close()

    @property
    def ready(self) -> bool:
        return self.started and self.pool.ready

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

    async def create(self, *, name: str, config: MapConfig, mode: Mode) -> dict[str, Any]:
        record = self._new_record(name, config, mode)
        summary = await self.pool.call(record.id, "create", {"record": record.as_dict()})
        self._catalog.add(record)
        self._records[record.id] = record
        self.pool.track(record.id)
        return {**summary, "worker": self.pool.worker_of(record.id)}

    async def summary(self, map_id: str) -> dict[str, Any]:
        self.record(map_id)
        summary = await self.pool.call(map_id, "summary")
        return {**summary, "worker": self.pool.worker_of(map_id)}

    async def delete(self, map_id: str) -> None:
        self.record(map_id)
        self._catalog.remove(map_id)
        del self._records[map_id]
        self.pool.untrack(map_id)
        self.notifier.notify(map_id)
        await self.pool.call(map_id, "delete")

    async def set_mode(self, map_id: str, mode: Mode) -> dict[str, Any]:
        record = self.record(map_id)
        summary = await self.pool.call(map_id, "set_mode", {"mode": mode})
        self._catalog.set_mode(map_id, mode)
        self._records[map_id] = MapRecord(
            record.id, record.name, mode, record.config, record.created
        )
        return {**summary, "worker": self.pool.worker_of(map_id)}

    # ------------------------------------------------------------ frames and queries
    async def submit(
        self, map_id: str, frame: dict[str, Any], image: bytes | None = None
    ) -> dict[str, Any]:
        """One frame to its map; the worker's reply (result, replayed, event ids, ...).

        With `image`, `frame` is the meta of an image frame (PNG/JPEG bytes, decoded by
        the map's worker)."""
        self.record(map_id)
        payload: dict[str, Any] = {"frame": frame}
        if image is not None:
            payload["image"] = image
        reply: dict[str, Any] = await self.pool.call(map_id, "frame", payload)
        if reply.get("event_ids"):
            self.notifier.notify(map_id)
        return reply

    async def query(self, map_id: str, op: str, **params: Any) -> Any:
        self.record(map_id)
        return await self.pool.call(map_id, op, params)

    def read_events(self, map_id: str, after: int) -> EventRows:
        """Stored events of a map after id `after`: (id, kind, data JSON) (blocking I/O)."""
        return self.store.read_events(map_id, after)

    def latest_event_id(self, map_id: str) -> int:
        """The id of the map's newest stored event, 0 if none (blocking I/O)."""
        self.record(map_id)
        return self.store.latest_event_id(map_id)

    # ------------------------------------------------------------ export / import
    async def export(self, map_id: str) -> bytes:
        """The map's export document as JSON bytes (serialised in the worker)."""
        self.record(map_id)
        timeout = max(self.settings.workers.request_timeout_s, 600.0)
        text: bytes = await self.pool.call(map_id, "export", timeout_s=timeout)
        return text

    async def import_map(self, body: bytes) -> dict[str, Any]:
        """A new map from an export document (bytes; parsed, checked and replayed by the
        worker that will own the new map, so a large document never blocks the API)."""
        map_id = self._new_id()
        payload = {
            "id": map_id,
            "created": time.time(),
            "body": body,
            "default_cap": self.settings.default_landmark_cap,
        }
        timeout = max(self.settings.workers.request_timeout_s, 600.0)
        reply = await self.pool.call(map_id, "import", payload, timeout_s=timeout)
        record = MapRecord.from_dict(reply["record"])
        self._catalog.add(record)
        self._records[record.id] = record
        self.pool.track(record.id)
        return {**reply["summary"], "worker": self.pool.worker_of(record.id)}
