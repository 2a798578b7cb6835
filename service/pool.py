"""The worker pool: one process per worker, maps placed by load, answers on the event loop.

GTSAM holds the GIL for each call, so the maps live in worker processes and the
API's event loop only awaits their answers. A map is run by one worker at a time; a
worker takes its requests strictly in order, so a map's frames are applied in arrival
order while maps on different workers proceed in parallel.

Placement: maps are dealt out to the workers in turn; a map with no frame yet is dealt
again at its first frame, to the worker with the fewest busy maps (`_deal`). Every
`workers.balance_interval_s` the pool compares the workers' loads and may move one map
(service.balance; `move`): new calls for the map wait in the API process, the old
worker answers what it already had, snapshots the map and closes it (`CloseMap`), the
new worker opens it from that snapshot (`OpenMap`), and the waiting calls go there. A
move that fails leaves the map where it was.

Transport: one socket pair per worker (``multiprocessing.Pipe``). The worker blocks on
``Connection.recv_bytes``; the API side never blocks: it writes the same
length-prefixed frames non-blockingly (``loop.add_writer`` when the pipe is full) and
reads answers in a ``loop.add_reader`` callback, without helper threads. An answer may
carry the map's new published view (service.published), handed to `on_view`; message
id 0 is a view sent unasked.

A worker that dies shows as end-of-file on its socket: the requests in flight get
`WorkerUnavailable` (the API answers 503 + Retry-After), a new process is started,
and it first re-opens the worker's maps from the store (snapshot + log tail). A
request that takes longer than the timeout gets the same 503; the frame log makes
a client's retry safe either way. At shutdown the pool closes the workers'
connections and waits (`workers.shutdown_timeout_s`) while each snapshots its maps.
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
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any, TypeVar

from service import worker
from service.balance import MOVE_COOLDOWN_S, SETTLE_INTERVALS, MapLoad, choose_move
from service.engine import Engine, reply_value
from service.errors import WorkerUnavailable
from service.requests import CloseMap, CreateMap, OpenMap, Ping, Request, SubmitFrame
from service.settings import Settings

log = logging.getLogger(__name__)

T = TypeVar("T")

_HEADER = struct.Struct("!i")  # multiprocessing.Connection's framing (messages < 2 GiB)


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


class WorkerPool(Engine):
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
        self._owner: dict[str, int] = {}
        self._next_owner = 0
        self._load: dict[str, MapLoad] = {}
        self._moving: dict[str, asyncio.Future[None]] = {}
        self._empty: set[str] = set()
        """Maps with no frame yet: their first frame deals them to a worker anew."""
        self._heading: dict[str, int] = {}
        """Maps being dealt at their first frame: the worker they go to."""
        self.deals = 0
        """Maps moved at their first frame (not counted in `moves`)."""
        self._leaning: tuple[int, int] | None = None
        """(from, to) workers of the move the balancer's last look would have made."""

    # ------------------------------------------------------------ lifecycle
    async def start(self, maps: Iterable[str]) -> None:
        """Start the workers; every known map is opened on its worker in the background
        (`ready` turns true when all are loaded; calls meanwhile queue behind the loads)."""
        self._loop = asyncio.get_running_loop()
        self._maps = set(maps)
        count = self._settings.workers.count
        self._owner = {m: i % count for i, m in enumerate(sorted(self._maps))}
        self._slots = [self._spawn(i) for i in range(count)]
        for slot in self._slots:
            self._spawn_load(slot)
        interval = self._settings.workers.balance_interval_s
        if interval > 0 and count > 1:
            self._background(self._balance_every(interval))

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
        mine = [m for m in self._maps if self._owner.get(m) == slot.index]
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
                        elif reply["value"]["frames"] == 0:
                            self._empty.add(map_id)
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
        # each worker snapshots its maps when its connection closes, then ends
        deadline = time.monotonic() + self._settings.workers.shutdown_timeout_s
        for slot in self._slots:
            await asyncio.to_thread(slot.process.join, max(0.0, deadline - time.monotonic()))
            if slot.process.is_alive():
                log.warning("worker %d did not end in time; killed", slot.index)
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
                "maps": sorted(m for m in self._maps if self._owner.get(m) == s.index),
                "load": round(
                    sum(
                        self._load[m].load
                        for m, w in self._owner.items()
                        if w == s.index and m in self._load
                    ),
                    3,
                ),
            }
            for s in self._slots
        ]

    def worker_of(self, map_id: str) -> int:
        """The worker running the map; a map new to the pool goes to the next worker in
        turn (a new map has no load to go by yet, and maps created together land on
        different workers; the balancer moves it if its worker turns out busier)."""
        owner = self._owner.get(map_id)
        if owner is None:
            owner = self._owner[map_id] = self._next_owner
            self._next_owner = (owner + 1) % self._settings.workers.count
        return owner

    def busy(self, map_id: str) -> bool:
        return map_id in self._moving or bool(self._slots[self.worker_of(map_id)].pending)

    def track(self, map_id: str) -> None:
        super().track(map_id)
        self.worker_of(map_id)

    def untrack(self, map_id: str) -> None:
        super().untrack(map_id)
        self._load.pop(map_id, None)
        self._owner.pop(map_id, None)
        self._empty.discard(map_id)

    # ------------------------------------------------------------ balance
    async def _balance_every(self, interval_s: float) -> None:
        settle = 0
        while True:
            await asyncio.sleep(interval_s)
            try:
                if settle > 0:  # sample only: the loads after the last move settle
                    settle -= 1
                    self._sample(interval_s)
                elif await self.balance(interval_s) is not None:
                    settle = SETTLE_INTERVALS
            except Exception:
                log.exception("balancing the maps over the workers failed")

    def _sample(self, interval_s: float) -> tuple[dict[int, float], dict[int, dict[str, float]]]:
        """Fold the last interval into every map's load: (each worker's load, the loads
        of the maps that may move, per worker)."""
        now = time.monotonic()
        totals = {s.index: 0.0 for s in self._slots}
        movable: dict[int, dict[str, float]] = {s.index: {} for s in self._slots}
        for map_id, load in self._load.items():
            owner = self._owner.get(map_id)
            level = load.sample(now, interval_s)
            if owner is None or map_id not in self._maps:
                continue
            totals[owner] += level
            if now - load.moved >= MOVE_COOLDOWN_S:
                movable[owner][map_id] = level
        return totals, movable

    async def balance(self, interval_s: float) -> tuple[str, int, int] | None:
        """Sample the maps' loads and move at most one map (see `choose_move`), if the
        previous look would have moved one between the same two workers too; the move
        made, or None."""
        choice = choose_move(*self._sample(interval_s))
        leaning, self._leaning = self._leaning, None if choice is None else choice[1:]
        if choice is None or leaning != choice[1:]:
            return None
        self._leaning = None
        map_id, _, target = choice
        return choice if await self.move(map_id, target) else None

    async def _deal(self, map_id: str) -> None:
        """A map's first frame: move it to the worker with the fewest busy maps (this
        one left out) if its own has more; it has no state yet, so the move only opens
        an empty map. Ties stay."""
        self._empty.discard(map_id)
        source = self.worker_of(map_id)
        now = time.monotonic()
        busy = {s.index: 0 for s in self._slots}
        for other, load in self._load.items():
            worker = self._heading.get(other, self._owner.get(other))
            if other != map_id and worker is not None and load.active(now):
                busy[worker] += 1
        target = min(busy, key=lambda w: (busy[w], w != source))
        if busy[target] >= busy[source]:
            return
        self._heading[map_id] = target
        try:
            if await self.move(map_id, target, balancing=False):
                self.deals += 1
        finally:
            del self._heading[map_id]

    async def move(self, map_id: str, target: int, *, balancing: bool = True) -> bool:
        """Move a map to worker `target`: calls meanwhile wait; the old worker answers
        what it has, snapshots and closes the map; the new one opens it. False when the
        map stays where it was (unknown, already there or moving, the old worker failed).
        `balancing`: a balancer's move (counted in `moves`; the map stays for
        MOVE_COOLDOWN_S), not a deal at the map's first frame."""
        source = self._owner.get(map_id)
        if source is None or source == target or map_id in self._moving:
            return False
        assert self._loop is not None
        gate: asyncio.Future[None] = self._loop.create_future()
        self._moving[map_id] = gate
        try:
            timeout = max(self._settings.workers.request_timeout_s, 600.0)
            reply = await asyncio.wait_for(
                self._request(self._slots[source], map_id, CloseMap()), timeout
            )
            if not reply["ok"]:
                log.error("map %s could not leave worker %d: %s", map_id, source, reply)
                return False
            self._owner[map_id] = target
            if balancing:
                self._load.setdefault(map_id, MapLoad()).moved = time.monotonic()
                self.moves += 1
            log.info("map %s moved from worker %d to worker %d", map_id, source, target)
            self._background(self._open(self._slots[target], map_id))
            return True
        except (_WorkerDied, TimeoutError):
            log.warning("map %s stays on worker %d (it stopped or did not answer)", map_id, source)
            return False
        finally:
            del self._moving[map_id]
            gate.set_result(None)

    async def _open(self, slot: _Slot, map_id: str) -> None:
        """Open a map on its new worker ahead of its calls (they queue behind it)."""
        try:
            reply = await self._request(slot, map_id, OpenMap())
            if not reply["ok"]:
                log.error("worker %d: map %s did not open: %s", slot.index, map_id, reply)
        except _WorkerDied:
            log.warning("worker %d died while opening map %s", slot.index, map_id)

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
            view = reply.get("view")
            if view is not None and self.on_view is not None:
                try:
                    self.on_view(view)
                except Exception:
                    log.exception("publishing the view of map %s failed", view.map_id)
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
        timeout, retry_after = self._limits(timeout_s)
        load = self._load.setdefault(map_id, MapLoad())
        load.change(+1, time.monotonic())
        try:
            if map_id in self._empty and isinstance(request, SubmitFrame):
                await self._deal(map_id)
            while (gate := self._moving.get(map_id)) is not None:
                await asyncio.shield(gate)  # the map is moving: to its new worker afterwards
            slot = self._slots[self.worker_of(map_id)]
            future = self._request(slot, map_id, request)
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
        finally:
            load.change(-1, time.monotonic())
        load.served(reply.get("busy_s", 0.0))
        if isinstance(request, CreateMap) and reply["ok"]:
            self._empty.add(map_id)
        return reply_value(reply, retry_after_s=retry_after)
