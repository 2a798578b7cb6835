"""The worker pool: one process per worker, maps pinned by id, answers on the event loop.

GTSAM holds the GIL for each call, so the maps live in worker processes and the
API's event loop only awaits their answers. A map always goes to the same worker
(``crc32(id) % count``); a worker takes its requests strictly in order, so a
map's frames are applied in arrival order while maps on different workers
proceed in parallel.

Transport: one socket pair per worker (``multiprocessing.Pipe``). The worker
blocks on ``Connection.recv_bytes``; the API side never blocks: it writes the
same length-prefixed frames non-blockingly (``loop.add_writer`` when the pipe is
full, e.g. a large import while the worker computes) and reads answers in a
``loop.add_reader`` callback. No helper threads, so a request costs two process
hand-offs and nothing more.

A worker that dies shows as end-of-file on its socket: the requests in flight get
`WorkerUnavailable` (the API answers 503 + Retry-After), a new process is started,
and it first re-opens the worker's maps from the store (snapshot + log tail). A
request that takes longer than the timeout gets the same 503; the frame log makes
a client's retry safe either way.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import multiprocessing
import os
import pickle
import struct
import time
import zlib
from collections.abc import Callable, Coroutine, Iterable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any, Protocol, TypeVar

from service import worker
from service.errors import ServiceError, WorkerUnavailable
from service.requests import OpenMap, Ping, Request
from service.settings import Settings

log = logging.getLogger(__name__)

T = TypeVar("T")

_HEADER = struct.Struct("!i")  # multiprocessing.Connection's framing (messages < 2 GiB)


class Engine(Protocol):
    """Runs the maps and answers calls on them: local worker processes (`WorkerPool`)
    or Ray actors (service.ray_engine.RayEngine)."""

    restarts: int
    """Workers (or actors) seen to stop and come back."""
    shared: bool
    """Other API processes may run maps of the same store (look maps up in the catalogue)."""

    async def start(self, maps: Iterable[str]) -> None: ...
    async def stop(self) -> None: ...
    @property
    def ready(self) -> bool: ...
    def status(self) -> list[dict[str, Any]]: ...
    def worker_of(self, map_id: str) -> int | None: ...
    def track(self, map_id: str) -> None: ...
    def untrack(self, map_id: str) -> None: ...
    async def call(self, map_id: str, request: Request[T], *, timeout_s: float | None = None) -> T:
        """Carry out `request` on the map; its answer, or raise ServiceError /
        WorkerUnavailable."""
        ...


def make_engine(settings: Settings, *, on_restart: Callable[[int], None] | None = None) -> Engine:
    """The engine `settings.engine` names."""
    if settings.engine == "ray":
        from service.ray_engine import RayEngine

        return RayEngine(settings, on_restart=on_restart)
    return WorkerPool(settings, on_restart=on_restart)


def reply_value(reply: dict[str, Any], *, retry_after_s: int) -> Any:
    """A worker's answer (service.worker.call): its value, or its error raised;
    `WorkerUnavailable` when the map's store could not be reached (retry later)."""
    if reply["ok"]:
        return reply["value"]
    if reply.get("unavailable"):
        raise WorkerUnavailable(reply["unavailable"], retry_after_s=retry_after_s)
    raise ServiceError.from_dict(reply["error"])


class _WorkerDied(Exception):
    pass


@dataclass
class _Slot:
    index: int
    process: BaseProcess
    conn: Connection
    generation: int = 0
    pid: int | None = None
    loading: int = 0
    """Maps still being re-opened after a (re)start."""
    started: float = field(default_factory=time.monotonic)
    pending: dict[int, asyncio.Future[Any]] = field(default_factory=dict)
    inbox: bytearray = field(default_factory=bytearray)
    outbox: bytearray = field(default_factory=bytearray)
    alive: bool = True
    up: bool = False
    """The worker answered its first ping (its imports are done)."""


class EngineBase:
    """What both engines keep: the maps they run, their background tasks, the restarts
    they saw, and the time limits of a call."""

    shared = False

    def __init__(
        self, settings: Settings, *, on_restart: Callable[[int], None] | None = None
    ) -> None:
        self._settings = settings
        self._maps: set[str] = set()
        self._on_restart = on_restart
        self._tasks: set[asyncio.Task[None]] = set()
        self.restarts = 0

    def track(self, map_id: str) -> None:
        self._maps.add(map_id)

    def untrack(self, map_id: str) -> None:
        self._maps.discard(map_id)

    def _background(self, work: Coroutine[Any, Any, None]) -> None:
        """Run `work` on the event loop, cancelled by `_cancel_background`."""
        task = asyncio.get_running_loop().create_task(work)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _cancel_background(self) -> None:
        for task in self._tasks:
            task.cancel()

    def _limits(self, timeout_s: float | None) -> tuple[float, int]:
        """(a call's time limit, s; the Retry-After of a 503, s)."""
        workers = self._settings.workers
        timeout = timeout_s if timeout_s is not None else workers.request_timeout_s
        return timeout, workers.retry_after_s


class WorkerPool(EngineBase):
    """Routes calls to the worker owning a map; restarts crashed workers (the `local`
    engine)."""

    def __init__(
        self, settings: Settings, *, on_restart: Callable[[int], None] | None = None
    ) -> None:
        super().__init__(settings, on_restart=on_restart)
        self._ctx = multiprocessing.get_context("spawn")
        self._slots: list[_Slot] = []
        self._ids = itertools.count(1)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopping = False

    # ------------------------------------------------------------ lifecycle
    async def start(self, maps: Iterable[str]) -> None:
        """Start the workers; every known map is opened on its worker in the background
        (`ready` turns true when all are loaded; calls meanwhile queue behind the loads)."""
        self._loop = asyncio.get_running_loop()
        self._maps = set(maps)
        self._slots = [self._spawn(i) for i in range(self._settings.workers.count)]
        for slot in self._slots:
            self._spawn_load(slot)

    def _spawn(self, index: int, generation: int = 0) -> _Slot:
        assert self._loop is not None
        parent, child = self._ctx.Pipe(duplex=True)
        process = self._ctx.Process(
            target=worker.serve,
            args=(child, self._settings.model_dump(mode="json"), index),
            name=f"covslam-worker-{index}",
            daemon=True,
        )
        process.start()
        child.close()
        slot = _Slot(index, process, parent, generation=generation, pid=process.pid)
        os.set_blocking(parent.fileno(), False)
        self._loop.add_reader(parent.fileno(), self._on_readable, slot)
        return slot

    def _spawn_load(self, slot: _Slot) -> None:
        mine = [m for m in self._maps if self.worker_of(m) == slot.index]
        slot.loading = len(mine)

        async def load() -> None:
            try:
                await self._request(slot, "", Ping())
                slot.up = True
                opens = [self._request(slot, m, OpenMap()) for m in mine]
                for map_id, coro in zip(mine, opens, strict=True):
                    try:
                        reply = await coro
                        if not reply["ok"]:
                            log.error(
                                "worker %d: map %s did not open: %s", slot.index, map_id, reply
                            )
                    finally:
                        slot.loading = max(0, slot.loading - 1)
            except _WorkerDied:
                log.warning("worker %d died while loading its maps", slot.index)

        self._background(load())

    async def stop(self) -> None:
        self._stopping = True
        self._cancel_background()
        for slot in self._slots:
            self._close(slot)
        for slot in self._slots:
            slot.process.join(timeout=5)
            if slot.process.is_alive():
                slot.process.kill()

    def _close(self, slot: _Slot) -> None:
        if not slot.alive:
            return
        slot.alive = False
        assert self._loop is not None
        fd = slot.conn.fileno()
        self._loop.remove_reader(fd)
        self._loop.remove_writer(fd)
        slot.conn.close()

    @property
    def ready(self) -> bool:
        return bool(self._slots) and all(s.up and s.loading == 0 and s.alive for s in self._slots)

    def status(self) -> list[dict[str, Any]]:
        return [
            {
                "index": s.index,
                "pid": s.pid,
                "up": s.up,
                "generation": s.generation,
                "loading": s.loading,
                "maps": sorted(m for m in self._maps if self.worker_of(m) == s.index),
            }
            for s in self._slots
        ]

    def worker_of(self, map_id: str) -> int:
        return zlib.crc32(map_id.encode()) % self._settings.workers.count

    # ------------------------------------------------------------ transport
    def _send(self, slot: _Slot, message: bytes) -> None:
        slot.outbox += _HEADER.pack(len(message))
        slot.outbox += message
        if len(slot.outbox) == len(message) + _HEADER.size:
            self._flush(slot)

    def _flush(self, slot: _Slot) -> None:
        assert self._loop is not None
        if not slot.alive:
            return
        try:
            sent = os.write(slot.conn.fileno(), slot.outbox)
        except BlockingIOError:
            sent = 0
        except OSError:
            self._died(slot)
            return
        del slot.outbox[:sent]
        if slot.outbox:
            self._loop.add_writer(slot.conn.fileno(), self._flush, slot)
        else:
            self._loop.remove_writer(slot.conn.fileno())

    def _on_readable(self, slot: _Slot) -> None:
        try:
            while True:
                chunk = os.read(slot.conn.fileno(), 1 << 20)
                if not chunk:
                    self._died(slot)
                    return
                slot.inbox += chunk
        except BlockingIOError:
            pass
        except OSError:
            self._died(slot)
            return
        while len(slot.inbox) >= _HEADER.size:
            (size,) = _HEADER.unpack_from(slot.inbox)
            if len(slot.inbox) < _HEADER.size + size:
                break
            payload = bytes(slot.inbox[_HEADER.size : _HEADER.size + size])
            del slot.inbox[: _HEADER.size + size]
            request_id, reply = pickle.loads(payload)
            future = slot.pending.pop(request_id, None)
            if future is not None and not future.done():
                future.set_result(reply)

    def _died(self, slot: _Slot) -> None:
        """End of file: the worker is gone. Fail its requests, start a new one."""
        if not slot.alive:
            return
        self._close(slot)
        for future in slot.pending.values():
            if not future.done():
                future.set_exception(_WorkerDied())
        slot.pending.clear()
        if self._stopping:
            return
        slot.process.join(timeout=0.1)
        self.restarts += 1
        log.warning(
            "worker %d (pid %s) stopped (exit code %s); restarting",
            slot.index,
            slot.pid,
            slot.process.exitcode,
        )
        fresh = self._spawn(slot.index, generation=slot.generation + 1)
        self._slots[slot.index] = fresh
        if self._on_restart is not None:
            self._on_restart(slot.index)
        self._spawn_load(fresh)

    def _request(self, slot: _Slot, map_id: str, request: Request[Any]) -> asyncio.Future[Any]:
        assert self._loop is not None
        request_id = next(self._ids)
        future: asyncio.Future[Any] = self._loop.create_future()
        slot.pending[request_id] = future
        self._send(slot, pickle.dumps((request_id, map_id, request), protocol=5))
        return future

    # ------------------------------------------------------------ calls
    async def call(self, map_id: str, request: Request[T], *, timeout_s: float | None = None) -> T:
        """Carry out `request` on the map's worker; its answer, or raise ServiceError /
        WorkerUnavailable."""
        slot = self._slots[self.worker_of(map_id)]
        timeout, retry_after = self._limits(timeout_s)
        future = self._request(slot, map_id, request)
        try:
            reply = await asyncio.wait_for(future, timeout)
        except _WorkerDied as exc:
            raise WorkerUnavailable(
                f"the worker owning map {map_id!r} stopped while handling this request; "
                "it is being restarted and the map reloaded from its log",
                retry_after_s=retry_after,
            ) from exc
        except TimeoutError as exc:
            raise WorkerUnavailable(
                f"the worker owning map {map_id!r} did not answer within {timeout:g} s",
                retry_after_s=retry_after,
            ) from exc
        return reply_value(reply, retry_after_s=retry_after)
