"""Frames: POST one frame, JSON (bearing observations) or multipart (meta + image)."""

from __future__ import annotations

import re
import time
from typing import Any

from fastapi import APIRouter, Request, Response
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from api.auth import AUTH_ERRORS, MapWrite, may_write
from api.deps import MAP_ID_MAX, MapId, media_type, unsupported_media
from api.errors import service_problem, unavailable_problem
from api.metrics import Metrics
from api.models import FrameResult, Problem
from service.errors import ServiceError, WorkerUnavailable
from service.frame_results import FrameReply
from service.frames_io import admit_frame
from service.jsonio import loads_object
from service.maps import MapService

META_MAX_BYTES = 64 << 10
"""Largest `meta` part of an image frame, bytes."""

router = APIRouter(prefix="/v1/maps/{map_id}/frames", tags=["frames"], dependencies=[MapWrite])

_BODY = {
    "requestBody": {
        "required": True,
        "description": "a frame: JSON (see FrameIn), or multipart/form-data with `meta` (the "
        "frame JSON without observations) and `image` (a PNG or JPEG file part, in the "
        "size of the map's camera; its features become the frame's observations)",
        "content": {
            "application/json": {"schema": {"$ref": "#/components/schemas/FrameIn"}},
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "properties": {
                        "meta": {
                            "type": "string",
                            "description": "the frame JSON (FrameIn) without observations",
                        },
                        "image": {
                            "type": "string",
                            "format": "binary",
                            "description": "panorama or omni image, PNG or JPEG (8-bit, "
                            "grey or colour), width x height as the map's camera",
                        },
                    },
                    "required": ["meta", "image"],
                }
            },
        },
    }
}


@router.post(
    "",
    response_model=FrameResult,
    openapi_extra=_BODY,
    responses={
        **AUTH_ERRORS,
        400: {"model": Problem, "description": "malformed JSON, NaN/Infinity"},
        404: {"model": Problem, "description": "unknown map"},
        409: {
            "model": Problem,
            "description": "seq or stamp out of order, or a different "
            "frame with an already used (robot, seq)",
        },
        413: {"model": Problem, "description": "body or image too large"},
        415: {
            "model": Problem,
            "description": "body neither application/json nor multipart/form-data",
        },
        422: {
            "model": Problem,
            "description": "a field is missing or wrong (see `field`); an image that does "
            "not decode or does not fit the map's camera; a map without a camera",
        },
        503: {"model": Problem, "description": "the map's worker is restarting; retry"},
    },
)
async def post_frame(map_id: MapId, request: Request) -> Any:
    """Submit a frame; the result of processing it.

    `(robot, seq)` makes a submission idempotent: repeating a frame returns the stored
    result (header `Idempotent-Replayed: true`); a lower seq than the robot's last is a 409.
    An image frame's retry must repeat the image too.
    """
    t0 = time.perf_counter()
    # the app's state directly: every dependency FastAPI resolves costs a frame CPU time
    state = request.app.state
    service: MapService = state.service
    metrics: Metrics = state.metrics
    service.record(map_id)
    ctype = media_type(request)
    if ctype not in ("application/json", "multipart/form-data"):
        raise unsupported_media(request, "application/json or multipart/form-data")
    settings = state.settings
    try:
        if ctype == "multipart/form-data":
            limit = settings.api.max_image_bytes
            meta, image = await read_image_frame(request, max_image_bytes=limit)
            admit_frame(meta, settings.frames, image_frame=True)
            reply = await service.submit(map_id, meta, image)
        else:
            # checked against the frame model and settings.frames by the map's worker,
            # in the one parse that reads it
            body = loads_object(await request.body(), "a frame")
            reply = await service.submit(map_id, body)
    except ServiceError as exc:
        metrics.rejected.labels(str(exc.status)).inc()
        raise
    return _answer(metrics, map_id, reply, t0)


def _answer(metrics: Metrics, map_id: str, reply: FrameReply, t0: float) -> Response:
    """A submitted frame's answer (its metrics noted; `t0`: perf_counter at the start)."""
    metrics.record_frame(map_id, reply, 1e3 * (time.perf_counter() - t0))
    # The worker's JSON text goes out as stored: the same bytes for a retry.
    headers = {"Idempotent-Replayed": "true"} if reply.replayed else None
    return Response(reply.result_json, media_type="application/json", headers=headers)


_FRAMES_PATH = re.compile(r"/v1/maps/([^/]+)/frames")
"""The route's path (a path parameter matches anything but a slash)."""


class FramesLane:
    """ASGI middleware: a JSON frame (POST /v1/maps/{map_id}/frames), most of the
    service's requests, without FastAPI's routing and dependency resolution (a third of
    the API process's CPU a frame).

    A request takes the lane up to its frame's submission only when the route would
    take it that far: the key allowed to write the map (the route's dependency, called
    directly: `may_write`), the map known, an id the route accepts, a JSON object body.
    Any other request goes to the route, with the body it was sent, and gets the
    route's answer; the body limits apply as to the route (this runs inside
    api.errors.BodyLimit). After the submission the lane answers as the route does:
    the frame's result, or the problem of the error the submission raised (the same
    functions, api.errors)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "POST" or scope.get("root_path"):
            await self.app(scope, receive, send)  # the lifespan too
            return
        match = _FRAMES_PATH.fullmatch(scope["path"])
        request = Request(scope, receive)
        if match is None or len(match[1]) > MAP_ID_MAX or media_type(request) != "application/json":
            await self.app(scope, receive, send)
            return
        t0 = time.perf_counter()
        raw = await request.body()
        map_id = match[1]
        frame = await _admitted(request, map_id, raw)
        if frame is None:
            await self.app(scope, _replaying(raw, receive), send)
            return
        state = request.app.state
        response: Response
        try:
            reply = await state.service.submit(map_id, frame)
        except ServiceError as exc:
            state.metrics.rejected.labels(str(exc.status)).inc()
            response = service_problem(request, exc)
        except WorkerUnavailable as exc:
            response = unavailable_problem(request, exc)
        else:
            response = _answer(state.metrics, map_id, reply, t0)
        await response(scope, receive, send)


async def _admitted(request: Request, map_id: str, raw: bytes) -> dict[str, Any] | None:
    """The frame object of a request the route would take as far as its submission;
    None for any other (nothing changed yet: the route answers it)."""
    try:
        await may_write(request, map_id)
        request.app.state.service.record(map_id)
        return loads_object(raw, "a frame")
    except Exception:
        return None


def _replaying(raw: bytes, receive: Receive) -> Receive:
    """`receive` with the body read already in front."""
    sent = False

    async def again() -> Message:
        nonlocal sent
        if sent:
            return await receive()
        sent = True
        return {"type": "http.request", "body": raw, "more_body": False}

    return again


def _form_error(detail: str, field: str | None = None) -> ServiceError:
    return ServiceError(422, "invalid-image-frame", "Invalid image frame", detail, field=field)


async def read_image_frame(
    request: Request, *, max_image_bytes: int
) -> tuple[dict[str, Any], bytes]:
    """The `meta` object and the `image` bytes of a multipart image frame.

    Raises ServiceError: 422 for a malformed form, a missing part, meta that is not a
    JSON object; 413 for an image over `max_image_bytes`.
    """
    if not request.headers.get("content-type", "").lower().startswith("multipart/form-data"):
        raise _form_error(
            f"content-type: {request.headers.get('content-type')!r}; an image frame is "
            "multipart/form-data (a meta part and an image file part)"
        )
    try:
        async with request.form(max_files=1, max_fields=2, max_part_size=META_MAX_BYTES) as form:
            meta_part = form.get("meta")
            image_part = form.get("image")
            if meta_part is None:
                raise _form_error("meta: part is required (the frame JSON)", "meta")
            if image_part is None:
                raise _form_error("image: part is required (a PNG or JPEG file)", "image")
            if not isinstance(image_part, UploadFile):
                raise _form_error(
                    "image: must be a file part (a filename in its Content-Disposition, as "
                    "curl -F image=@pano.png sends it)",
                    "image",
                )
            if image_part.size is not None and image_part.size > max_image_bytes:
                raise ServiceError(
                    413,
                    "image-too-large",
                    "Image too large",
                    f"image: {image_part.size} bytes exceed the limit of {max_image_bytes} bytes",
                )
            image = await image_part.read()
            raw = await meta_part.read() if isinstance(meta_part, UploadFile) else meta_part
    except HTTPException as exc:  # Starlette's answer to a malformed multipart body
        raise _form_error(f"multipart body: {exc.detail}") from exc
    if len(image) > max_image_bytes:
        raise ServiceError(
            413,
            "image-too-large",
            "Image too large",
            f"image: {len(image)} bytes exceed the limit of {max_image_bytes} bytes",
        )
    try:
        meta = loads_object(raw.encode() if isinstance(raw, str) else raw, "the frame's meta")
    except ServiceError as exc:
        detail = exc.detail.removeprefix("body: ")
        raise _form_error(f"meta: {detail}", "meta") from exc
    return meta, image
