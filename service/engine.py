"""What runs the maps for the API process: the `Engine` interface, and what its two
implementations share.

An engine answers calls on maps: the local worker processes (service.pool.WorkerPool,
the `local` engine) or Ray actors (service.ray_engine.RayEngine, the `ray` engine).
Both get a worker's answer as service.worker.call makes it and turn it into the
request's value or its error (`reply_value`).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Coroutine, Iterable
from typing import Any, Protocol, TypeVar

from service.errors import ServiceError, WorkerUnavailable
from service.published import ViewDelta
from service.requests import Request
from service.settings import Settings

T = TypeVar("T")


class Engine(Protocol):
    """Runs the maps and answers calls on them: local worker processes (service.pool.WorkerPool)
    or Ray actors (service.ray_engine.RayEngine)."""

    restarts: int
    """Workers (or actors) seen to stop and come back."""
    moves: int
    """Maps moved from one worker to another (balancing)."""
    shared: bool
    """Other API processes may run maps of the same store (look maps up in the catalogue)."""
    on_view: Callable[[ViewDelta], None] | None
    """Called with each published view of a map, as sent (engines whose workers publish
    them)."""

    async def start(self, maps: Iterable[str]) -> None: ...
    async def stop(self) -> None: ...
    @property
    def ready(self) -> bool: ...
    def status(self) -> list[dict[str, Any]]: ...
    def worker_of(self, map_id: str) -> int | None: ...
    def busy(self, map_id: str) -> bool:
        """The map's worker has requests in flight (a call would wait)."""
        ...

    def track(self, map_id: str) -> None: ...
    def untrack(self, map_id: str) -> None: ...
    async def call(self, map_id: str, request: Request[T], *, timeout_s: float | None = None) -> T:
        """Carry out `request` on the map; its answer, or raise ServiceError /
        WorkerUnavailable."""
        ...


def reply_value(reply: dict[str, Any], *, retry_after_s: int) -> Any:
    """A worker's answer (service.worker.call): its value, or its error raised;
    `WorkerUnavailable` when the map's store could not be reached (retry later)."""
    if reply["ok"]:
        return reply["value"]
    if reply.get("unavailable"):
        raise WorkerUnavailable(reply["unavailable"], retry_after_s=retry_after_s)
    raise ServiceError.from_dict(reply["error"])


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
        self.moves = 0
        """Maps moved from one worker to another (balancing)."""
        self.on_view: Callable[[ViewDelta], None] | None = None
        """Called with every published view a worker sends (the local pool's workers)."""

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
