"""Frames: POST one frame (JSON; the multipart image form answers 501 for now)."""

from __future__ import annotations

import time
from typing import Any

from fastapi import APIRouter, Request, Response

from api.deps import MapId, MetricsDep, ServiceDep
from api.errors import problem
from api.models import FrameResult, Problem
from service.errors import ServiceError
from service.jsonio import loads_object

router = APIRouter(prefix="/v1/maps/{map_id}/frames", tags=["frames"])

_BODY = {
    "requestBody": {
        "required": True,
        "description": "a frame: JSON (see FrameIn), or multipart `meta` (the frame JSON "
        "without observations) + `image` (PNG/JPEG; not implemented yet: 501)",
        "content": {
            "application/json": {"schema": {"$ref": "#/components/schemas/FrameIn"}},
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "properties": {
                        "meta": {"type": "string", "description": "frame JSON, no observations"},
                        "image": {
                            "type": "string",
                            "format": "binary",
                            "description": "panorama or omni image, PNG or JPEG",
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
        400: {"model": Problem, "description": "malformed JSON, NaN/Infinity"},
        404: {"model": Problem, "description": "unknown map"},
        409: {
            "model": Problem,
            "description": "seq or stamp out of order, or a different "
            "frame with an already used (robot, seq)",
        },
        413: {"model": Problem, "description": "body too large"},
        422: {"model": Problem, "description": "a field is missing or wrong (see `field`)"},
        501: {"model": Problem, "description": "image frames are not implemented yet"},
        503: {"model": Problem, "description": "the map's worker is restarting; retry"},
    },
)
async def post_frame(
    map_id: MapId, request: Request, service: ServiceDep, metrics: MetricsDep
) -> Any:
    """Submit a frame; the result of processing it.

    `(robot, seq)` makes a submission idempotent: repeating a frame returns the stored
    result (header `Idempotent-Replayed: true`); a lower seq than the robot's last is a 409.
    """
    t0 = time.perf_counter()
    service.record(map_id)
    ctype = request.headers.get("content-type", "")
    if ctype.startswith("multipart/"):
        metrics.rejected.labels("501").inc()
        return problem(
            501,
            "not-implemented",
            "Image frames not implemented",
            "content-type: multipart image frames (meta + image) arrive with the image "
            "frontend; post the JSON form with bearing observations for now",
            instance=request.url.path,
        )
    try:
        body = loads_object(await request.body(), "a frame")
        reply = await service.submit(map_id, body)
    except ServiceError as exc:
        metrics.rejected.labels(str(exc.status)).inc()
        raise
    metrics.record_frame(map_id, reply, 1e3 * (time.perf_counter() - t0))
    # The worker's JSON text goes out as stored: the same bytes for a retry.
    headers = {"Idempotent-Replayed": "true"} if reply["replayed"] else None
    return Response(reply["result_json"], media_type="application/json", headers=headers)
