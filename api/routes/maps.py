"""Maps: create, list, summary, mode, delete, export and import."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request, Response, status

from api.auth import AUTH_ERRORS, AdminOnly, MapAdmin, MapRead
from api.deps import JsonOnly, MapId, MetricsDep, ServiceDep
from api.models import MapBrief, MapCreate, MapPatch, MapPublic, Problem

router = APIRouter(prefix="/v1/maps", tags=["maps"])

_FULL: dict[int | str, dict[str, Any]] = {
    413: {"model": Problem, "description": "body over the limit"},
    415: {"model": Problem, "description": "body not application/json"},
    507: {"model": Problem, "description": "the service holds max_maps maps, or its disk is full"},
}
_ERRORS: dict[int | str, dict[str, Any]] = {
    **AUTH_ERRORS,
    404: {"model": Problem, "description": "unknown map"},
    503: {"model": Problem, "description": "the map's worker is restarting; see Retry-After"},
}


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=MapPublic,
    responses={**AUTH_ERRORS, **_FULL, 422: {"model": Problem}},
    dependencies=[AdminOnly, JsonOnly],
)
async def create_map(body: MapCreate, service: ServiceDep, response: Response) -> dict[str, Any]:
    """Create a map; its `id` names it in every other path."""
    summary = await service.create(name=body.name, config=body.config, mode=body.mode)
    response.headers["Location"] = f"/v1/maps/{summary['id']}"
    return summary


@router.get("", response_model=list[MapBrief], responses=AUTH_ERRORS, dependencies=[AdminOnly])
async def list_maps(service: ServiceDep) -> list[dict[str, Any]]:
    """Every map (id, name, mode, config, created)."""
    return [r.as_dict() for r in service.list()]


@router.post(
    "/import",
    status_code=status.HTTP_201_CREATED,
    response_model=MapPublic,
    responses={
        **AUTH_ERRORS,
        **_FULL,
        400: {"model": Problem, "description": "malformed JSON"},
        422: {"model": Problem, "description": "not a valid map document"},
    },
    dependencies=[AdminOnly, JsonOnly],
    openapi_extra={
        "requestBody": {
            "required": True,
            "description": "a document from GET /v1/maps/{id}/export (format covslam.map, "
            "version 1); its frame log is replayed into a new map",
            "content": {"application/json": {"schema": {"type": "object"}}},
        }
    },
)
async def import_map(request: Request, service: ServiceDep, response: Response) -> dict[str, Any]:
    """Restore an exported map as a new map (new id)."""
    # The worker parses and checks the document: a large body never holds the API's GIL.
    summary = await service.import_map(await request.body())
    response.headers["Location"] = f"/v1/maps/{summary['id']}"
    return summary


@router.get("/{map_id}", response_model=MapPublic, responses=_ERRORS, dependencies=[MapRead])
async def get_map(map_id: MapId, service: ServiceDep) -> dict[str, Any]:
    """Summary: counts, config, estimator parameters, timing stats."""
    return await service.summary(map_id)


@router.patch(
    "/{map_id}", response_model=MapPublic, responses=_ERRORS, dependencies=[MapAdmin, JsonOnly]
)
async def patch_map(map_id: MapId, body: MapPatch, service: ServiceDep) -> dict[str, Any]:
    """Switch between mapping and localisation (frozen map: no new landmarks)."""
    return await service.set_mode(map_id, body.mode)


@router.delete(
    "/{map_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    responses=_ERRORS,
    dependencies=[MapAdmin],
)
async def delete_map(map_id: MapId, service: ServiceDep, metrics: MetricsDep) -> Response:
    """Delete a map and its store."""
    await service.delete(map_id)
    metrics.forget(map_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.get("/{map_id}/export", responses=_ERRORS, dependencies=[MapRead])
async def export_map(map_id: MapId, service: ServiceDep) -> Response:
    """The whole map as one versioned JSON document (format covslam.map, version 1):
    map record and config, estimator parameters, landmarks with covariances and
    observation statistics, trajectories, removal log, and the frame log with results."""
    text = await service.export(map_id)  # JSON bytes, serialised by the worker
    return Response(
        text,
        media_type="application/json",
        headers={"Content-Disposition": f'attachment; filename="covslam-map-{map_id}.json"'},
    )
