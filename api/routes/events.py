"""Server-sent events of a map: frame results and map changes, resumable by id."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import APIRouter, Header, Query, Request
from fastapi.responses import StreamingResponse

from api.auth import AUTH_ERRORS, Principal, StreamRead
from api.deps import MapId, ServiceDep
from api.models import Problem
from service.maps import MapService

router = APIRouter(prefix="/v1/maps/{map_id}/events", tags=["events"])

KEEPALIVE_S = 15.0


async def _stream(
    service: MapService, map_id: str, after: int, request: Request, who: Principal
) -> AsyncIterator[bytes]:
    """The map's events after `after`; ends when the client goes, the map is deleted, or
    the key the stream was opened with is revoked."""
    yield b": covslam events\n\n"
    batch_s = service.settings.api.event_batch_s
    while True:
        if who.key is not None and not service.key_alive(who.key):
            return
        wake = service.notifier.handle(map_id)
        after, chunk = await service.events_after(map_id, after)
        if chunk:  # one write for everything since the last one
            yield chunk
            if batch_s > 0:
                await asyncio.sleep(batch_s)
            continue
        if await request.is_disconnected() or not service.exists(map_id):
            return
        try:
            async with asyncio.timeout(KEEPALIVE_S):
                await wake.wait()
        except TimeoutError:
            yield b": keepalive\n\n"


@router.get(
    "",
    responses={
        200: {
            "content": {"text/event-stream": {"schema": {"type": "string"}}},
            "description": "events `frame` (a frame result), `landmark_added` {id, label, x, y "
            "[m], frame_id}, `landmark_marginalised` (a removal record with reason), "
            "`landmark_restored` {id, label, x, y [m], restorations, frame_id} (an archived "
            "landmark back under its id); each has "
            "an `id` for Last-Event-ID",
        },
        **AUTH_ERRORS,
        404: {"model": Problem},
    },
)
async def stream_events(
    map_id: MapId,
    request: Request,
    service: ServiceDep,
    who: Annotated[Principal, StreamRead],
    last_event_id: Annotated[
        str | None, Header(description="resume after this event id (set by EventSource)")
    ] = None,
    since: Annotated[
        int | None,
        Query(
            ge=0,
            description="start after this event id (0 = every stored event); "
            "default: only new events",
        ),
    ] = None,
) -> StreamingResponse:
    """Live stream (SSE) of frame results and map changes."""
    service.record(map_id)
    if last_event_id is not None and last_event_id.strip().isdigit():
        after = int(last_event_id)
    elif since is not None:
        after = since
    else:
        after = await asyncio.to_thread(service.latest_event_id, map_id)
    return StreamingResponse(
        _stream(service, map_id, after, request, who),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )
