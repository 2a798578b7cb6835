"""The `ray` engine: each map a named, detached Ray actor; the API process routes.

A map's actor is named ``map-<id>`` in the deployment's namespace, created on first
use (``get_if_exists``) wherever Ray's scheduler puts it (``SPREAD`` over the
nodes), detached (it outlives the API process that created it) and restarted
without limit (``max_restarts=-1``). Its constructor reloads the map from the store
(latest snapshot + log tail), exactly as a local worker does after a crash, and it
answers every call with the same code as a local worker (service.worker.call). The
API process holds no map state, so several API processes can serve one cluster
(look-ups of maps they did not create go to the catalogue).

Failover: a call in flight when the actor's process dies fails (``max_task_retries=0``;
the API answers 503 + Retry-After); Ray restarts the actor on a live node, and calls
made meanwhile wait for it. The frame log is committed before a frame is processed
and ``(robot, seq)`` makes a retry idempotent, so a client that retries loses and
duplicates nothing. Snapshots are taken in the actor right after the call that made
one due.

With more than one machine the store must be PostgreSQL (every node reaches it); a
SQLite directory works only while every actor runs on the API's machine.
"""

from __future__ import annotations

import asyncio
import logging
import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, TypeVar

from service import worker
from service.engine import Engine, reply_value
from service.errors import WorkerUnavailable
from service.requests import CreateMap, DeleteMap, ImportMap, OpenMap, Request
from service.settings import Settings
from service.store import is_postgres_url

try:
    import ray
except ImportError:
    ray = None  # type: ignore[assignment,unused-ignore]  # Ray installed or not

log = logging.getLogger(__name__)

T = TypeVar("T")

RAY_MISSING = "--engine ray needs Ray, which is not installed: pip install 'covslam[ray]'"


def actor_name(map_id: str) -> str:
    return f"map-{map_id}"


class MapActor:
    """One map in a Ray actor process (wrapped by `ray.remote` in `RayEngine`)."""

    def __init__(self, settings: dict[str, Any], map_id: str) -> None:
        worker.init_worker(settings, 0, own_signals=False)
        self.map_id = map_id
        self.opened: dict[str, Any] | None = None
        try:
            if worker.has_map(map_id):  # a restart: reload from the store now
                self.opened = worker.call(map_id, OpenMap())
        except Exception:  # e.g. the store is unreachable: the first call opens the map
            log.exception("map %s: not reloaded at the actor's start", map_id)
        if self.opened is not None and not self.opened["ok"]:
            log.error("map %s did not open: %s", map_id, self.opened)

    def call(self, request: Request[Any]) -> dict[str, Any]:
        """`request` on this actor's map, as a local worker answers it."""
        reply = worker.call(self.map_id, request)
        worker.snapshot_if_due(self.map_id)
        return reply

    def where(self) -> dict[str, Any]:
        """The actor's process id and node id."""
        return {"pid": os.getpid(), "node": ray.get_runtime_context().get_node_id()}


def _actor_errors() -> tuple[type[BaseException], ...]:
    names = ("RayActorError", "ActorDiedError", "ActorUnavailableError")
    return tuple(getattr(ray.exceptions, n) for n in names if hasattr(ray.exceptions, n))


class RayEngine(Engine):
    """Routes calls to the maps' actors (service.engine.Engine)."""

    shared = True

    def __init__(
        self, settings: Settings, *, on_restart: Callable[[int], None] | None = None
    ) -> None:
        if ray is None:
            raise RuntimeError(RAY_MISSING)
        super().__init__(settings, on_restart=on_restart)
        # actors run in Ray's working directory: a relative store path would move
        self._settings_doc = settings.model_dump(mode="json")
        self._settings_doc["data_dir"] = str(settings.data_dir.resolve())
        url = settings.store.url
        if url is not None and not is_postgres_url(url):
            self._settings_doc["store"]["url"] = str(Path(url).resolve())
        self._cls = ray.remote(MapActor)
        self._actors: dict[str, Any] = {}
        self._where: dict[str, dict[str, Any]] = {}
        self._connected = False
        self._loading = 0

    # ------------------------------------------------------------ lifecycle
    async def start(self, maps: Iterable[str]) -> None:
        """Join the cluster; make sure every known map has its actor (in the background:
        `ready` turns true once each answered)."""
        cfg = self._settings.ray
        address = None if cfg.address == "local" else cfg.address
        await asyncio.to_thread(
            ray.init,
            address=address,
            namespace=cfg.namespace,
            ignore_reinit_error=True,
            log_to_driver=False,
            logging_level=logging.WARNING,
        )
        self._connected = True
        self._maps = set(maps)
        self._loading = len(self._maps)
        self._background(self._load(sorted(self._maps)))

    async def _load(self, maps: list[str]) -> None:
        async def one(map_id: str) -> None:
            try:
                await self._locate(map_id)
            except Exception:
                log.exception("map %s: its actor did not answer", map_id)
            finally:
                self._loading = max(0, self._loading - 1)

        await asyncio.gather(*(one(m) for m in maps))

    async def stop(self) -> None:
        """Leave the cluster; the actors (detached) keep serving other API processes."""
        self._cancel_background()
        if self._connected:
            await asyncio.to_thread(ray.shutdown)
            self._connected = False

    @property
    def ready(self) -> bool:
        return self._connected and self._loading == 0

    def status(self) -> list[dict[str, Any]]:
        """One entry per map actor: its map, up (it answered since it was (re)started),
        pid and node, and loading (1 until it answered, as a local worker's count)."""
        return [
            {
                "map": m,
                "up": m in self._where,
                "loading": int(m not in self._where),
                **self._where.get(m, {"pid": None, "node": None}),
            }
            for m in sorted(self._maps)
        ]

    def worker_of(self, map_id: str) -> int | None:
        return None

    def busy(self, map_id: str) -> bool:
        return True  # no published views: reads go to the actor anyway

    # ------------------------------------------------------------ actors
    def _create(self, map_id: str) -> Any:
        cfg = self._settings.ray
        return self._cls.options(
            name=actor_name(map_id),
            namespace=cfg.namespace,
            lifetime="detached",
            get_if_exists=True,
            max_restarts=-1,
            max_task_retries=0,
            num_cpus=cfg.actor_cpus,
            scheduling_strategy="SPREAD",
        ).remote(self._settings_doc, map_id)

    async def _actor(self, map_id: str) -> Any:
        actor = self._actors.get(map_id)
        if actor is None:
            actor = await asyncio.to_thread(self._create, map_id)
            self._actors[map_id] = actor
        return actor

    async def _locate(self, map_id: str) -> None:
        actor = await self._actor(map_id)
        self._where[map_id] = await asyncio.wrap_future(actor.where.remote().future())

    def _kill(self, map_id: str) -> None:
        actor = self._actors.pop(map_id, None)
        self._where.pop(map_id, None)
        if actor is not None:
            ray.kill(actor, no_restart=True)

    # ------------------------------------------------------------ calls
    async def call(self, map_id: str, request: Request[T], *, timeout_s: float | None = None) -> T:
        timeout, retry_after = self._limits(timeout_s)
        actor = await self._actor(map_id)
        ref = actor.call.remote(request)
        try:
            reply = await asyncio.wait_for(asyncio.wrap_future(ref.future()), timeout)
        except _actor_errors() as exc:
            self.restarts += 1
            self._where.pop(map_id, None)
            self._actors.pop(map_id, None)  # the next call finds (or makes) it by name
            if self._on_restart is not None:
                self._on_restart(-1)
            raise WorkerUnavailable(
                f"the actor of map {map_id!r} stopped while handling this request; Ray "
                "restarts it and it reloads the map from the store",
                retry_after_s=retry_after,
            ) from exc
        except TimeoutError as exc:
            raise WorkerUnavailable(
                f"the actor of map {map_id!r} did not answer within {timeout:g} s",
                retry_after_s=retry_after,
            ) from exc
        created = isinstance(request, CreateMap | ImportMap)
        if isinstance(request, DeleteMap) or (created and not reply["ok"]):
            await asyncio.to_thread(self._kill, map_id)
        elif map_id not in self._where:
            self._background(self._locate(map_id))
        value: T = reply_value(reply, retry_after_s=retry_after)
        return value
