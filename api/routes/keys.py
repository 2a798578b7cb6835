"""A map's API keys: create (the key is shown once), list (ids and scopes), delete."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Path, Response, status

from api.auth import AUTH_ERRORS, MapAdmin
from api.deps import MapId, ServiceDep
from api.models import KeyCreate, KeyCreated, KeyPublic, Problem

router = APIRouter(prefix="/v1/maps/{map_id}/keys", tags=["keys"], dependencies=[MapAdmin])

_ERRORS: dict[int | str, dict[str, Any]] = {
    **AUTH_ERRORS,
    404: {"model": Problem, "description": "unknown map or key"},
}


@router.post("", status_code=status.HTTP_201_CREATED, response_model=KeyCreated, responses=_ERRORS)
async def create_key(map_id: MapId, body: KeyCreate, service: ServiceDep) -> dict[str, Any]:
    """A new key for this map (admin key or the map's admin scope). The response is the
    only time the key is shown: the service stores its sha256."""
    key, secret = service.create_key(map_id, body.scope)
    return {"id": key.id, "key": secret, "scope": key.scope}


@router.get("", response_model=list[KeyPublic], responses=_ERRORS)
async def list_keys(map_id: MapId, service: ServiceDep) -> list[dict[str, Any]]:
    """The map's keys: ids, scopes and creation times (never the keys)."""
    return [{"id": k.id, "scope": k.scope, "created": k.created} for k in service.keys(map_id)]


@router.delete(
    "/{key_id}", status_code=status.HTTP_204_NO_CONTENT, response_class=Response, responses=_ERRORS
)
async def delete_key(
    map_id: MapId,
    key_id: Annotated[str, Path(max_length=64, description="the key's id")],
    service: ServiceDep,
) -> Response:
    """Revoke a key: requests with it get 401 from now on."""
    service.delete_key(map_id, key_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
