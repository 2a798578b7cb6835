"""The map document of export and import (format ``covslam.map``, version 1).

Export: the map record and config, the estimator's parameters, landmarks with
covariances and observation statistics, trajectories, the removal log and the
frame log with each frame's result. Import replays the frame log into a new map
(frames are validated like any posted frame; nothing in the document is trusted
as estimator state).

A camera map's image frames carry the image's digest (``"image"``) and the
labelled observations the front end made of the image, not the image; the
document's ``frontend`` member is the front end's state at export (each live
landmark's descriptors and view directions, candidate tracks, each robot's last
pose: JSON, descriptors in base64). Import feeds those observations to the
estimator and then restores that state, so the new map goes on associating images
as the old one would.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from typing import Any

from service.errors import ServiceError
from service.frame_log import IMPORTED_FRONTEND
from service.jsonio import loads_object
from service.pipeline.config import MapConfig, Mode, slam_config_dict
from service.pipeline.images import parse_state_doc
from service.queries import Landmarks, Trajectory
from service.requests import MapRequest
from service.session import MapSession

EXPORT_FORMAT = "covslam.map"
EXPORT_VERSION = 1


def _bad_import(field: str, detail: str) -> ServiceError:
    return ServiceError(
        422, "invalid-import", "Invalid map document", f"{field}: {detail}", field=field
    )


MAP_NAME_MAX_CHARS = 200
"""Longest map name (POST /v1/maps and imports alike)."""


def name_problem(name: Any) -> str | None:
    """What is wrong with a map name, or None: a non-empty string of at most
    MAP_NAME_MAX_CHARS characters of valid Unicode (no lone surrogate)."""
    if not isinstance(name, str) or not name:
        return "must be a non-empty string"
    if len(name) > MAP_NAME_MAX_CHARS:
        return f"must be at most {MAP_NAME_MAX_CHARS} characters, got {len(name)}"
    if any("\ud800" <= c <= "\udfff" for c in name):
        return "must be valid Unicode text (it holds a lone surrogate)"
    return None


def parse_export(raw: bytes) -> tuple[str, Mode, MapConfig, list[Any], Any]:
    """Check an export document: (name, mode, config, frames, front-end state or None);
    ServiceError 400/422. The front-end state is checked by the import itself."""
    doc = loads_object(raw, "a covslam.map document")
    if doc.get("format") != EXPORT_FORMAT:
        raise _bad_import("format", f"must be {EXPORT_FORMAT!r}, got {doc.get('format')!r}")
    if doc.get("version") != EXPORT_VERSION:
        raise _bad_import(
            "version", f"version {doc.get('version')!r} unsupported (this is {EXPORT_VERSION})"
        )
    meta = doc.get("map")
    if not isinstance(meta, dict):
        raise _bad_import("map", "must be an object with name, mode and config")
    name, mode = meta.get("name"), meta.get("mode")
    problem = name_problem(name)
    if problem is not None or not isinstance(name, str):
        raise _bad_import("map.name", problem or "must be a string")
    if mode not in ("mapping", "localisation"):
        raise _bad_import("map.mode", f"must be 'mapping' or 'localisation', got {mode!r}")
    try:
        config = MapConfig.model_validate(meta.get("config"))
    except ValueError as exc:
        raise _bad_import("map.config", str(exc)) from exc
    frames = doc.get("frames")
    if not isinstance(frames, list):
        raise _bad_import("frames", "must be an array of {frame, result}")
    return name, mode, config, frames, doc.get("frontend")


def export_map(session: MapSession) -> dict[str, Any]:
    """The map document. An image frame carries its image's digest and the
    observations the front end made of it (not the image); a camera map's document
    has the front end's state (`frontend`: landmark descriptors, tracks, last poses)."""
    frames = []
    for stored in session.store.frames_after(0):
        body = json.loads(stored.body)
        if "image" in body:
            observations = session.store.image_observations(stored.id)
            if observations is None:
                raise ServiceError(
                    422,
                    "not-exportable",
                    "Map cannot be exported",
                    f"frame {stored.id} (robot {stored.robot!r} seq {stored.seq}): an "
                    "image frame whose observations were not recorded (logged by an "
                    "older version); an export carries observations, not images",
                )
            body["observations"] = observations
        frames.append(
            {
                "frame": body,
                "result": None if stored.result is None else json.loads(stored.result),
            }
        )
    images = session.pipeline.images
    front = {} if images is None else {"frontend": images.state_doc()}
    return {
        "format": EXPORT_FORMAT,
        "version": EXPORT_VERSION,
        "exported": time.time(),
        "map": session.record.as_dict(),
        "estimator": slam_config_dict(session.slam.config),
        "landmarks": Landmarks().answer(session),
        "trajectories": Trajectory().answer(session),
        "removals": session.store.removals(),
        "frames": frames,
        **front,
    }


@dataclass(frozen=True)
class Export(MapRequest[bytes]):
    """The map's export document as compact JSON bytes (serialised in the worker, so a
    large map never holds the API's GIL)."""

    def answer(self, session: MapSession) -> bytes:
        return json.dumps(export_map(session), separators=(",", ":")).encode()


def import_frames(session: MapSession, frames: list[dict[str, Any]], frontend: Any = None) -> None:
    """Replay an export's frame log into this (new, empty) map; then put back the
    front end's state of a camera map (`frontend`, the export's; without it the
    front end starts afresh: its landmarks have no descriptors to match)."""
    if frontend is not None and session.vision is None:
        raise _bad_import("frontend", "a front-end state for a map without a camera")
    if frontend is not None and session.vision is not None:
        try:  # refuse a bad state before replaying anything
            parse_state_doc(frontend, session.vision.front_end.associator.config)
        except ValueError as exc:
            raise ServiceError(
                422, "invalid-import", "Invalid map document", str(exc), field="frontend"
            ) from exc
    for i, item in enumerate(frames):
        if not isinstance(item, dict) or not isinstance(item.get("frame"), dict):
            raise _bad_import(f"frames[{i}].frame", "must be a frame object")
        try:
            session.submit(item["frame"], imported="image" in item["frame"])
        except ServiceError as exc:
            raise _bad_import(f"frames[{i}].frame", exc.detail) from exc
    if frontend is not None and session.pipeline.images is not None:
        session.pipeline.images.set_state_doc(frontend)
        session.store.set_meta(IMPORTED_FRONTEND, {"after": session.last_log_id, "state": frontend})
    session.snapshot()
