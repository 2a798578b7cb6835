"""What runs inside a worker process: the maps it owns and one call per request.

The API process sends ``call(op, map_id, payload)`` through a
``ProcessPoolExecutor`` of one process; calls are taken strictly in order, so a
map's frames are applied in the order they arrived. A map is opened on first use
(latest snapshot + log tail) and kept open. Every answer is a plain dict:
``{"ok": True, "value": ...}`` or ``{"ok": False, "error": ServiceError.as_dict()}``.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from service.errors import ServiceError, unknown_map
from service.session import MapSession, remove_map_files
from service.settings import Settings
from service.store import MapRecord, map_db_path

log = logging.getLogger(__name__)

_settings: Settings | None = None
_sessions: dict[str, MapSession] = {}


def init_worker(settings: dict[str, Any], index: int) -> None:
    """Process initialiser: settings from the parent, logging."""
    global _settings
    _settings = Settings.model_validate(settings)
    logging.basicConfig(
        level=_settings.log_level.upper(),
        format=f"%(asctime)s %(levelname)s worker{index} %(name)s: %(message)s",
    )


def _cfg() -> Settings:
    if _settings is None:
        raise RuntimeError("worker not initialised")
    return _settings


def _path(map_id: str) -> Path:
    return map_db_path(_cfg().data_dir, map_id)


def _session(map_id: str) -> MapSession:
    session = _sessions.get(map_id)
    if session is None:
        if not _path(map_id).exists():
            raise unknown_map(map_id)
        session = MapSession(_path(map_id), _cfg().store)
        _sessions[map_id] = session
    return session


def _ping(map_id: str, payload: dict[str, Any]) -> dict[str, Any]:
    return {"pid": os.getpid(), "maps": sorted(_sessions)}


def _create(map_id: str, payload: dict[str, Any]) -> dict[str, Any]:
    record = MapRecord.from_dict(payload["record"])
    old = _sessions.pop(map_id, None)
    if old is not None:
        old.close()
    _sessions[map_id] = MapSession.create(_path(map_id), record, _cfg().store)
    return _sessions[map_id].summary()


def _open(map_id: str, payload: dict[str, Any]) -> dict[str, Any]:
    return {"frames": _session(map_id).slam.frame_count}


def _delete(map_id: str, payload: dict[str, Any]) -> None:
    session = _sessions.pop(map_id, None)
    if session is not None:
        session.close()
    remove_map_files(_path(map_id))


def _import(map_id: str, payload: dict[str, Any]) -> dict[str, Any]:
    _create(map_id, payload)
    try:
        _sessions[map_id].import_frames(payload["frames"])
    except BaseException:
        _delete(map_id, {})
        raise
    return _sessions[map_id].summary()


def _set_mode(map_id: str, payload: dict[str, Any]) -> dict[str, Any]:
    session = _session(map_id)
    session.set_mode(payload["mode"])
    return session.summary()


_OPS: dict[str, Callable[[str, dict[str, Any]], Any]] = {
    "ping": _ping,
    "create": _create,
    "open": _open,
    "delete": _delete,
    "import": _import,
    "set_mode": _set_mode,
    "frame": lambda m, p: _session(m).submit(p["frame"]),
    "summary": lambda m, p: _session(m).summary(),
    "pose": lambda m, p: _session(m).pose(),
    "trajectory": lambda m, p: _session(m).trajectory(p.get("robot")),
    "landmarks": lambda m, p: _session(m).landmarks(),
    "coverage": lambda m, p: _session(m).coverage(**p),
    "export": lambda m, p: _session(m).export(),
}


def call(op: str, map_id: str, payload: dict[str, Any]) -> dict[str, Any]:
    """Run one operation on one map; never raises (errors come back as data)."""
    try:
        return {"ok": True, "value": _OPS[op](map_id, payload)}
    except ServiceError as exc:
        return {"ok": False, "error": exc.as_dict()}
    except Exception as exc:
        log.exception("op %s on map %s failed", op, map_id)
        error = ServiceError(500, "internal", "Internal error", f"{type(exc).__name__}: {exc}")
        return {"ok": False, "error": error.as_dict()}
