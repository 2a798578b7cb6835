"""Places (the particle-filter place localiser): not implemented yet, 501."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from api.deps import MapId, ServiceDep
from api.errors import problem
from api.models import Problem

router = APIRouter(prefix="/v1/maps/{map_id}/places", tags=["places"])

_501: dict[int | str, dict[str, Any]] = {
    501: {"model": Problem, "description": "the place localiser arrives with its issue"}
}


def _not_yet(request: Request) -> JSONResponse:
    return problem(
        501,
        "not-implemented",
        "Places not implemented",
        "places: the place localiser (learnt places, transitions, global localisation) "
        "is not implemented yet",
        instance=request.url.path,
    )


@router.get("", responses=_501)
async def list_places(map_id: MapId, request: Request, service: ServiceDep) -> JSONResponse:
    """Learnt places and the transitions between them (501 for now)."""
    service.record(map_id)
    return _not_yet(request)


@router.post("", responses=_501)
async def learn_place(map_id: MapId, request: Request, service: ServiceDep) -> JSONResponse:
    """Learn a place at the robot's current pose now (501 for now)."""
    service.record(map_id)
    return _not_yet(request)
