"""Places of the particle-filter place localiser: list them, learn one now."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from api.auth import AUTH_ERRORS, MapRead, MapWrite
from api.deps import JsonOnly, MapId, ServiceDep
from api.models import PlaceLearnIn, PlaceLearnt, PlacesOut, Problem
from service.queries import LearnPlace, Places

router = APIRouter(prefix="/v1/maps/{map_id}/places", tags=["places"])

_ERRORS: dict[int | str, dict[str, Any]] = {
    **AUTH_ERRORS,
    404: {"model": Problem, "description": "unknown map or robot"},
    503: {"model": Problem, "description": "the map's worker is restarting; see Retry-After"},
}


@router.get("", response_model=PlacesOut, responses=_ERRORS, dependencies=[MapRead])
async def list_places(map_id: MapId, service: ServiceDep) -> Any:
    """Learnt places (reference pose, landmarks with bearing, depth and its variance) and
    the transitions between consecutively visited places."""
    return await service.query(map_id, Places())


@router.post(
    "",
    response_model=PlaceLearnt,
    status_code=201,
    responses={
        **_ERRORS,
        409: {"model": Problem, "description": "robot not localised, or too few landmarks"},
        415: {"model": Problem, "description": "body not application/json"},
        422: {"model": Problem, "description": "invalid body"},
    },
    dependencies=[MapWrite, JsonOnly],
)
async def learn_place(map_id: MapId, service: ServiceDep, body: PlaceLearnIn | None = None) -> Any:
    """Learn a place at a robot's current pose now."""
    return await service.query(map_id, LearnPlace(None if body is None else body.robot))
