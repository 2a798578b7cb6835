"""The worker pool: one single-process executor per worker, maps pinned by id.

GTSAM holds the GIL for each call, so the maps live in worker processes and the
API's event loop only awaits their answers. A map always goes to the same worker
(``crc32(id) % count``); a worker takes its calls in order, so a map's frames are
applied in arrival order while maps on different workers proceed in parallel.

A worker that dies (``BrokenProcessPool``) is replaced by a new process, which
first re-opens the worker's maps from the store (snapshot + log tail); the calls
that were in flight get `WorkerUnavailable` (the API answers 503 + Retry-After).
A call that takes longer than the timeout gets the same answer; the frame log
makes a client's retry safe either way.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import time
import zlib
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import Any

from service import worker
from service.errors import ServiceError, WorkerUnavailable
from service.settings import Settings

log = logging.getLogger(__name__)


@dataclass
class _Slot:
    index: int
    executor: ProcessPoolExecutor
    generation: int = 0
    pid: int | None = None
    loading: int = 0
    """Maps still being re-opened after a (re)start."""
    started: float = field(default_factory=time.monotonic)


class WorkerPool:
    """Routes calls to the worker owning a map; restarts crashed workers."""

    def __init__(
        self, settings: Settings, *, on_restart: Callable[[int], None] | None = None
    ) -> None:
        self._settings = settings
        self._ctx = multiprocessing.get_context("spawn")
        self._slots: list[_Slot] = []
        self._maps: set[str] = set()
        self._on_restart = on_restart
        self._tasks: set[asyncio.Task[None]] = set()
        self.restarts = 0

    # ------------------------------------------------------------ lifecycle
    def _executor(self, index: int) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(
            max_workers=1,
            mp_context=self._ctx,
            initializer=worker.init_worker,
            initargs=(self._settings.model_dump(mode="json"), index),
        )

    async def start(self, maps: Iterable[str]) -> None:
        """Start the workers; every known map is opened on its worker in the background
        (`ready` turns true when all are loaded; calls meanwhile queue behind the loads)."""
        self._maps = set(maps)
        self._slots = [_Slot(i, self._executor(i)) for i in range(self._settings.workers.count)]
        for slot in self._slots:
            self._spawn_load(slot)

    def _spawn_load(self, slot: _Slot) -> None:
        slot.loading = sum(1 for m in self._maps if self.worker_of(m) == slot.index)

        async def load() -> None:
            try:
                await self._ping(slot)
                await self._reopen(slot)
            except BrokenProcessPool:
                log.warning("worker %d died while loading its maps", slot.index)

        task = asyncio.get_running_loop().create_task(load())
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def stop(self) -> None:
        for slot in self._slots:
            slot.executor.shutdown(wait=False, cancel_futures=True)
        for task in self._tasks:
            task.cancel()

    @property
    def ready(self) -> bool:
        return bool(self._slots) and all(s.loading == 0 for s in self._slots)

    def status(self) -> list[dict[str, Any]]:
        return [
            {
                "index": s.index,
                "pid": s.pid,
                "generation": s.generation,
                "loading": s.loading,
                "maps": sorted(m for m in self._maps if self.worker_of(m) == s.index),
            }
            for s in self._slots
        ]

    def worker_of(self, map_id: str) -> int:
        return zlib.crc32(map_id.encode()) % self._settings.workers.count

    def track(self, map_id: str) -> None:
        self._maps.add(map_id)

    def untrack(self, map_id: str) -> None:
        self._maps.discard(map_id)

    async def _ping(self, slot: _Slot) -> None:
        fut = slot.executor.submit(worker.call, "ping", "", {})
        reply = await asyncio.wrap_future(fut)
        slot.pid = reply["value"]["pid"]

    async def _reopen(self, slot: _Slot) -> None:
        """Open every map of this worker (its first calls after a start)."""
        mine = [m for m in self._maps if self.worker_of(m) == slot.index]
        slot.loading = len(mine)
        futures = [slot.executor.submit(worker.call, "open", m, {}) for m in mine]
        for map_id, fut in zip(mine, futures, strict=True):
            try:
                reply = await asyncio.wrap_future(fut)
                if not reply["ok"]:
                    log.error("worker %d: map %s did not open: %s", slot.index, map_id, reply)
            except BrokenProcessPool:
                return  # crashed again while loading: the next restart reloads
            finally:
                slot.loading = max(0, slot.loading - 1)

    def _restart(self, slot: _Slot, generation: int) -> None:
        """Replace a broken worker (once per generation) and reload its maps."""
        if slot.generation != generation:
            return  # someone else already restarted it
        slot.executor.shutdown(wait=False, cancel_futures=True)
        slot.executor = self._executor(slot.index)
        slot.generation += 1
        slot.pid = None
        slot.started = time.monotonic()
        self.restarts += 1
        log.warning("worker %d crashed; restarted (generation %d)", slot.index, slot.generation)
        if self._on_restart is not None:
            self._on_restart(slot.index)

        self._spawn_load(slot)

    async def watch(self, period_s: float = 0.5) -> None:
        """Restart workers that died while idle (run as a background task)."""
        while True:
            await asyncio.sleep(period_s)
            for slot in self._slots:
                if getattr(slot.executor, "_broken", False):
                    self._restart(slot, slot.generation)

    # ------------------------------------------------------------ calls
    async def call(
        self,
        map_id: str,
        op: str,
        payload: dict[str, Any] | None = None,
        *,
        timeout_s: float | None = None,
    ) -> Any:
        """Run `op` on the map's worker; its value, or raise ServiceError / WorkerUnavailable."""
        slot = self._slots[self.worker_of(map_id)]
        retry_after = self._settings.workers.retry_after_s
        generation = slot.generation
        try:
            fut = slot.executor.submit(worker.call, op, map_id, payload or {})
        except (BrokenProcessPool, RuntimeError):
            # Died while idle and nobody noticed yet: nothing of this call was sent.
            self._restart(slot, generation)
            generation = slot.generation
            fut = slot.executor.submit(worker.call, op, map_id, payload or {})
        timeout = timeout_s if timeout_s is not None else self._settings.workers.request_timeout_s
        try:
            reply = await asyncio.wait_for(asyncio.wrap_future(fut), timeout)
        except BrokenProcessPool as exc:
            self._restart(slot, generation)
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
        if not reply["ok"]:
            raise ServiceError.from_dict(reply["error"])
        return reply["value"]
