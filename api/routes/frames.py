"""Frames: POST one frame, JSON (bearing observations) or multipart (meta + image)."""

from __future__ import annotations

import time
from typing import Any

from fastapi import APIRouter, Request, Response
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException

from api.auth import AUTH_ERRORS, MapWrite
from api.deps import MapId, media_type, unsupported_media
from api.metrics import Metrics
from api.models import FrameResult, Problem
from service.errors import ServiceError
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
    metrics.record_frame(map_id, reply, 1e3 * (time.perf_counter() - t0))
    # The worker's JSON text goes out as stored: the same bytes for a retry.
    headers = {"Idempotent-Replayed": "true"} if reply.replayed else None
    return Response(reply.result_json, media_type="application/json", headers=headers)


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
