"""What runs inside a worker process: the maps it owns and one call per request.

`serve` is the process's main loop: it reads ``(message id, map_id, request)``
messages (a request of service.requests) from its connection to the API process (see
service.pool) and answers each in turn, strictly in order, so a map's frames are applied in
the order they arrived. A map is opened on first use
(latest snapshot + log tail) and kept open. Every answer is a plain dict:
``{"ok": True, "value": ...}`` or ``{"ok": False, "error": ServiceError.as_dict()}``;
an answer to a request that changed a map also carries the map's new published view
(``"view"``, a service.published.ViewDelta from the view sent before), and an idle
worker sends the views it refreshed unasked (message id 0). When the API process goes
away (its shutdown closes the connection), every open map that took frames since its
last snapshot is snapshotted before the process ends, so the next start replays no log.
"""

from __future__ import annotations

import logging
import os
import pickle
import queue
import signal
import threading
import time
from multiprocessing.connection import Connection
from typing import Any

from threadpoolctl import threadpool_limits

from frontend.pipeline import FrontEnd
from service.errors import ServiceError, internal_error, unknown_map
from service.exchange import import_frames, parse_export
from service.pipeline.config import camera_model, slam_config
from service.published import MapView, ViewDelta, build_view
from service.queries import LearnPlace, SetMode, Summary
from service.requests import (
    CloseMap,
    CreateMap,
    DeleteMap,
    ImportMap,
    MapRequest,
    OpenMap,
    Ping,
    RefreshView,
    Request,
    SubmitFrame,
)
from service.session import MapSession
from service.settings import Settings
from service.store import MapPlace, MapRecord, Store, connection_lost

log = logging.getLogger(__name__)

_settings: Settings | None = None
_store: Store | None = None
_sessions: dict[str, MapSession] = {}
_publish = False
"""Build published views (the local pool's workers; a Ray actor is asked directly)."""
_stale: set[str] = set()
"""Open maps whose published view has parts that lag behind the map."""
_views: dict[str, MapView] = {}
"""The latest view published of each open map (the base of the next one's delta)."""

_CHANGES = (SubmitFrame, SetMode, LearnPlace, OpenMap, CreateMap, ImportMap, RefreshView)
"""Requests after which a map's published view is rebuilt."""


def init_worker(settings: dict[str, Any], index: int, *, own_signals: bool = True) -> None:
    """Process initialiser: settings from the parent, logging. `own_signals`: ignore
    SIGINT and SIGTERM (a pool worker ends when the API process closes its pipe)."""
    global _settings, _store
    if own_signals:
        # Ctrl+C or a SIGTERM to the whole process group stops the API process, whose
        # shutdown closes our connection: we end on that end-of-file, after the call.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _settings = Settings.model_validate(settings)
    _store = None
    if _settings.workers.nice:
        os.nice(_settings.workers.nice)
    if _settings.workers.blas_threads:
        threadpool_limits(limits=_settings.workers.blas_threads, user_api="blas")
    logging.basicConfig(
        level=_settings.log_level.upper(),
        format=f"%(asctime)s %(levelname)s worker{index} %(name)s: %(message)s",
    )


def _cfg() -> Settings:
    if _settings is None:
        raise RuntimeError("worker not initialised")
    return _settings


def _place(map_id: str) -> MapPlace:
    global _store
    if _store is None:  # first use, or the store's server went away
        _store = _cfg().open_store()
    return _store.place(map_id)


def has_map(map_id: str) -> bool:
    """The map has a store (it was created and not deleted)."""
    return map_id in _sessions or _place(map_id).exists()


def _session(map_id: str) -> MapSession:
    session = _sessions.get(map_id)
    if session is None:
        place = _place(map_id)
        if not place.exists():
            raise unknown_map(map_id)
        session = MapSession(place, _cfg().store)
        _sessions[map_id] = session
    return session


def _create(map_id: str, request: CreateMap) -> dict[str, Any]:
    record = MapRecord.from_dict(request.record)
    try:  # the camera's and front end's own checks, which the config model cannot express
        camera = camera_model(record.config)
        if camera is not None:
            FrontEnd(camera).close()
    except ValueError as exc:
        detail = f"config.camera: {exc}"
        raise ServiceError(422, "invalid-config", "Invalid map config", detail) from exc
    old = _sessions.pop(map_id, None)
    if old is not None:
        old.close()
    _sessions[map_id] = MapSession.create(_place(map_id), record, _cfg().store)
    return Summary().answer(_sessions[map_id])


def _delete(map_id: str) -> None:
    session = _sessions.pop(map_id, None)
    _stale.discard(map_id)
    _views.pop(map_id, None)
    if session is not None:
        session.close()
    _place(map_id).remove()


def close_map(map_id: str) -> None:
    """Snapshot an open map if it took frames since its last snapshot, then close it."""
    session = _sessions.pop(map_id, None)
    _stale.discard(map_id)
    _views.pop(map_id, None)
    if session is None:
        return
    try:
        if session.unsnapshotted:
            session.snapshot()
    finally:
        session.close()


def close_all() -> None:
    """`close_map` for every open map (a failure is logged; the others still close)."""
    for map_id in list(_sessions):
        try:
            close_map(map_id)
        except Exception:
            log.exception("final snapshot of map %s failed", map_id)


def _import(map_id: str, request: ImportMap) -> dict[str, Any]:
    """A new map from an export document's bytes: parse, check, replay its frame log
    (in mapping mode, as it was built), then set the document's mode."""
    name, mode, config, frames, frontend = parse_export(request.body)
    config = config.with_default_cap(request.default_cap)
    try:
        slam_config(config.model_dump(mode="json"), mode)
    except ValueError as exc:
        detail = f"map.config: {exc}"
        raise ServiceError(422, "invalid-import", "Invalid map document", detail) from exc
    record = MapRecord(map_id, name, "mapping", config.model_dump(mode="json"), request.created)
    _create(map_id, CreateMap(record.as_dict()))
    try:
        session = _sessions[map_id]
        import_frames(session, frames, frontend)
        if mode != "mapping":
            session.set_mode(mode)
    except BaseException:
        _delete(map_id)
        raise
    return {"record": session.record.as_dict(), "summary": Summary().answer(session)}


def carry_out(map_id: str, request: Request[Any]) -> Any:
    """The answer to `request` on map `map_id` (errors raised)."""
    if isinstance(request, SubmitFrame):  # a posted frame: its limits are checked here
        return _session(map_id).submit(request.frame, request.image, limits=_cfg().frames)
    if isinstance(request, MapRequest):
        return request.answer(_session(map_id))
    if isinstance(request, Ping):
        return {"pid": os.getpid(), "maps": sorted(_sessions)}
    if isinstance(request, OpenMap):
        return {"frames": _session(map_id).slam.frame_count}
    if isinstance(request, CreateMap):
        return _create(map_id, request)
    if isinstance(request, ImportMap):
        return _import(map_id, request)
    if isinstance(request, CloseMap):
        close_map(map_id)
        return None
    if isinstance(request, RefreshView):
        _session(map_id)  # its view follows with the answer
        if request.whole:
            _views.pop(map_id, None)  # all of it is sent, and built anew
        return None
    if isinstance(request, DeleteMap):
        _delete(map_id)
        return None
    raise TypeError(f"not a request: {request!r}")


Message = tuple[Any, str, Request[Any]]
"""(message id, map id, request) as the API process sends it."""
IDLE_AFTER_S = 0.05
"""A worker with no request for this long is idle: it refreshes published views and
takes due snapshots (a client posting frame after frame sends its next one sooner)."""
_NOTHING = object()


def serve(conn: Connection, settings: dict[str, Any], index: int) -> None:
    """Main loop of a worker process; returns when the API process goes away.

    Requests are handled strictly in arrival order. A reader thread takes them from
    the pipe as they arrive (at most `workers.read_ahead` waiting; 0 = one at a time,
    no prefetch) and starts extracting the features of an image frame's image
    right away (OpenCV, without the GIL), while the current request computes.
    """
    global _publish
    init_worker(settings, index)
    _publish = True
    limit = _cfg().workers.read_ahead
    inbox: queue.Queue[Message | None] = queue.Queue(maxsize=max(1, limit))
    reader = threading.Thread(
        target=_reader, args=(conn, inbox, limit > 0), name="covslam-reader", daemon=True
    )
    reader.start()
    waiting: object = _NOTHING
    try:
        while True:
            request = inbox.get() if waiting is _NOTHING else waiting
            waiting = _NOTHING
            if request is None:  # end of the connection
                return
            assert isinstance(request, tuple)
            request_id, map_id, what = request
            reply = call(map_id, what)
            try:
                conn.send_bytes(pickle.dumps((request_id, reply), protocol=5))
            except (BrokenPipeError, OSError):
                return
            if isinstance(what, SubmitFrame):
                upkeep(map_id)
            try:  # a client that sends one request after the other is not idle
                waiting = inbox.get(timeout=IDLE_AFTER_S)
            except queue.Empty:
                _idle_work(inbox, conn)
    finally:
        close_all()


def _reader(conn: Connection, inbox: queue.Queue[Message | None], prefetch: bool) -> None:
    """Thread: requests from the pipe into `inbox`, in order; None at end of file."""
    while True:
        try:
            request: Message = pickle.loads(conn.recv_bytes())
        except (EOFError, OSError):
            inbox.put(None)
            return
        if prefetch:
            _prefetch(request)
        inbox.put(request)


def _prefetch(request: Message) -> None:
    """Start extracting the features of an image frame for an open camera map."""
    _, map_id, what = request
    image = what.image if isinstance(what, SubmitFrame) else None
    session = _sessions.get(map_id)
    if image is None or session is None or session.vision is None:
        return
    try:
        session.vision.prefetch(image)
    except RuntimeError:  # the map was closed meanwhile: its frame will say so
        log.debug("no prefetch for map %s (closed)", map_id)


def _idle_work(inbox: queue.Queue[Message | None], conn: Connection) -> None:
    """While no request is waiting, one map at a time: published views with parts that
    lag behind their map, renewed (sent unasked), then snapshots that are due."""
    for map_id in list(_stale):
        if not inbox.empty():
            return
        view = _view(map_id)
        if view is not None:
            try:
                conn.send_bytes(pickle.dumps((0, {"ok": True, "value": None, "view": view})))
            except (BrokenPipeError, OSError):
                return
    for map_id in list(_sessions):
        if not inbox.empty():
            return
        snapshot_if_due(map_id)


def _view(map_id: str, *, robot: str | None = None, refresh: bool = False) -> ViewDelta | None:
    """The open map's published view now, as a delta from the one sent before (None:
    not open, or it failed: logged); `robot`, `refresh`: see build_view (neither: all
    new)."""
    session = _sessions.get(map_id)
    if session is None:
        return None
    previous = _views.get(map_id)
    try:
        view = build_view(session, previous=previous, robot=robot, refresh=refresh)
    except Exception:
        log.exception("the published view of map %s failed", map_id)
        return None
    _views[map_id] = view
    if robot is None and not refresh:
        _stale.discard(map_id)
    else:
        _stale.add(map_id)
    return ViewDelta.between(view, previous)


def _published(map_id: str, request: Request[Any], value: Any) -> ViewDelta | None:
    """The view to publish after `request` answered `value` (None: nothing changed)."""
    if not isinstance(request, _CHANGES):
        return None
    if isinstance(request, SubmitFrame):
        if value.replayed:
            return None
        return _view(map_id, robot=request.frame.get("robot"))
    if isinstance(request, RefreshView):
        return _view(map_id, refresh=True)
    return _view(map_id)


def upkeep(map_id: str) -> None:
    """The open map's upkeep after a frame whose result was sent (MapSession.upkeep)."""
    session = _sessions.get(map_id)
    if session is None:
        return
    try:
        changed = session.upkeep()
    except Exception:
        log.exception("the upkeep of map %s failed", map_id)
        changed = True
    if changed:
        # The view published with the frame's answer predates the upkeep's removals and
        # the estimate they moved: renewed in idle time, or with the next frame.
        _stale.add(map_id)


def snapshot_if_due(map_id: str) -> None:
    """Snapshot an open map if its snapshot is due (a failure is logged, not raised)."""
    session = _sessions.get(map_id)
    if session is not None and session.snapshot_due:
        try:
            session.snapshot()
        except Exception:
            log.exception("snapshot of map %s failed", map_id)


def call(map_id: str, request: Request[Any]) -> dict[str, Any]:
    """Carry out one request on one map; never raises (errors come back as data)."""
    t0 = time.perf_counter()
    try:
        value = carry_out(map_id, request)
        reply = {"ok": True, "value": value}
        if _publish:  # a pool's worker: the view to publish and the pool's measure of load
            view = _published(map_id, request, value)
            if view is not None:
                reply["view"] = view
            reply["busy_s"] = time.perf_counter() - t0
        return reply
    except ServiceError as exc:
        return {"ok": False, "error": exc.as_dict()}
    except Exception as exc:
        if connection_lost(exc):
            return _store_lost(map_id, exc)
        log.exception("%s on map %s failed", type(request).__name__, map_id)
        return {"ok": False, "error": internal_error(exc).as_dict()}


def _store_lost(map_id: str, exc: Exception) -> dict[str, Any]:
    """The store's server went away: forget the map (the next call reloads it from the
    store, as after a crash) and the store's connection; the caller may retry (503)."""
    global _store
    log.warning("map %s: store connection lost (%s); the map reloads on its next call", map_id, exc)
    session = _sessions.pop(map_id, None)
    for closing in (session, _store):
        try:
            if closing is not None:
                closing.close()
        except Exception:
            log.debug("closing after a lost connection failed", exc_info=True)
    _store = None
    return {"ok": False, "unavailable": f"the store of map {map_id!r} is unreachable: {exc}"}
