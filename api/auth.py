"""Authentication and authorisation: API keys sent as ``Authorization: Bearer <key>``.

Who may do what (docs/deployment.md):

- the admin key (setting ``auth.admin_key``): everything, and it alone creates, lists
  and imports maps and reads /metrics;
- a map's key reaches that map only, within its scope: ``read`` (the map, its queries,
  export and event stream) < ``write`` (also frames and places) < ``admin`` (also mode,
  delete, the map's keys);
- no key, or a key the service does not know: 401 with ``WWW-Authenticate: Bearer``;
  a known key outside its map or scope: 403, the same answer whether or not the other
  map exists.

With auth off (no admin key, loopback bind only) every request acts as the admin.
EventSource cannot set headers, so the event stream also takes the key as the query
parameter ``access_token`` (and only that endpoint does).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import Depends, Query, Request, Security
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from api.deps import MapId
from api.models import Problem
from service.errors import ServiceError
from service.keys import Scope, allows, key_hash, same_hash
from service.maps import MapService
from service.settings import Settings
from service.store import KeyRecord

bearer = HTTPBearer(
    auto_error=False,
    description="an API key: the admin key (COVSLAM_AUTH__ADMIN_KEY) or a map's key "
    "from POST /v1/maps/{map_id}/keys",
)


AUTH_ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": Problem, "description": "no API key, or one the service does not know"},
    403: {
        "model": Problem,
        "description": "the key does not reach this map, or its scope does not allow this",
    },
}
"""The responses every protected operation declares."""


class AuthError(ServiceError):
    """401 or 403, with the headers the status calls for."""

    def __init__(self, status: int, detail: str, *, headers: dict[str, str] | None = None):
        slug, title = (
            ("unauthorised", "Unauthorised") if status == 401 else ("forbidden", "Forbidden")
        )
        super().__init__(status, slug, title, detail)
        self.headers = headers


def _unauthorised(detail: str, error: str | None = None) -> AuthError:
    challenge = 'Bearer realm="covslam"' + (f', error="{error}"' if error else "")
    return AuthError(401, detail, headers={"WWW-Authenticate": challenge})


@dataclass(frozen=True, slots=True)
class Principal:
    """Who is asking: the admin (the admin key, or anyone while auth is off) or a map key."""

    admin: bool
    key: KeyRecord | None = None


def identify(settings: Settings, service: MapService, token: str | None) -> Principal:
    """The principal a presented key stands for; AuthError 401 without a valid one."""
    admin_key = settings.auth.admin_key
    if admin_key is None:
        return Principal(admin=True)
    if not token:
        raise _unauthorised("Authorization: an API key is required (Authorization: Bearer <key>)")
    if same_hash(key_hash(token), key_hash(admin_key.get_secret_value())):
        return Principal(admin=True)
    key = service.find_key(token)
    if key is None:
        raise _unauthorised("Authorization: the key is not valid", "invalid_token")
    return Principal(admin=False, key=key)


async def principal(
    request: Request,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Security(bearer)],
) -> Principal:
    token = None if credentials is None else credentials.credentials
    return identify(request.app.state.settings, request.app.state.service, token)


async def stream_principal(
    request: Request,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Security(bearer)],
    access_token: Annotated[
        str | None,
        Query(
            max_length=200,
            description="the API key, for clients that cannot set headers (EventSource); "
            "prefer the Authorization header",
        ),
    ] = None,
) -> Principal:
    token = access_token if credentials is None else credentials.credentials
    return identify(request.app.state.settings, request.app.state.service, token)


PrincipalDep = Annotated[Principal, Depends(principal)]


async def admin_only(who: PrincipalDep) -> Principal:
    if not who.admin:
        raise AuthError(403, "this needs the service's admin key")
    return who


def _check_map(who: Principal, map_id: str, scope: Scope) -> Principal:
    if who.admin:
        return who
    assert who.key is not None
    if who.key.map_id != map_id:
        raise AuthError(403, "the key does not grant access to this map")
    if not allows(who.key.scope, scope):
        raise AuthError(
            403, f"the key's scope {who.key.scope!r} does not allow this (it needs {scope!r})"
        )
    return who


async def may_write(request: Request, map_id: str) -> Principal:
    """What the `MapWrite` dependency does, called directly (the frames lane,
    api.routes.frames.FramesLane): the request's key, then its map and scope.

    Raises AuthError as the dependency does."""
    return await map_write(map_id, await principal(request, await bearer(request)))


async def map_read(map_id: MapId, who: PrincipalDep) -> Principal:
    return _check_map(who, map_id, "read")


async def map_write(map_id: MapId, who: PrincipalDep) -> Principal:
    return _check_map(who, map_id, "write")


async def map_admin(map_id: MapId, who: PrincipalDep) -> Principal:
    return _check_map(who, map_id, "admin")


async def stream_read(
    map_id: MapId, who: Annotated[Principal, Depends(stream_principal)]
) -> Principal:
    return _check_map(who, map_id, "read")


AdminOnly = Depends(admin_only)
MapRead = Depends(map_read)
MapWrite = Depends(map_write)
MapAdmin = Depends(map_admin)
StreamRead = Depends(stream_read)
