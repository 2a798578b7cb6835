"""Dependencies of the routers (built in the app's lifespan, stored on app.state).

They are `async def` on purpose: FastAPI runs plain `def` dependencies in a thread pool,
which would add two thread hand-offs to every request.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Path, Request

from api.metrics import Metrics
from service.errors import ServiceError
from service.maps import MapService


async def get_service(request: Request) -> MapService:
    service: MapService = request.app.state.service
    return service


async def get_metrics(request: Request) -> Metrics:
    metrics: Metrics = request.app.state.metrics
    return metrics


ServiceDep = Annotated[MapService, Depends(get_service)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
MAP_ID_MAX = 64
"""The longest map id a path may name (a longer one is a 422)."""
MapId = Annotated[str, Path(description="the map's id (from POST /v1/maps)", max_length=MAP_ID_MAX)]


def media_type(request: Request) -> str:
    """The request's media type, lower case, without parameters ('' when absent)."""
    return request.headers.get("content-type", "").split(";", 1)[0].strip().lower()


def has_body(request: Request) -> bool:
    length = request.headers.get("content-length")
    return (length is not None and length != "0") or "transfer-encoding" in request.headers


def unsupported_media(request: Request, accepted: str) -> ServiceError:
    """415: the body's content type is not one this endpoint reads."""
    got = request.headers.get("content-type")
    return ServiceError(
        415,
        "unsupported-media-type",
        "Unsupported media type",
        f"content-type: {got!r}; this endpoint accepts {accepted}",
    )


async def require_json(request: Request) -> None:
    """A body, if there is one, must be application/json (a browser form cannot post it
    cross-site without a preflight, and no text/plain body is ever parsed as JSON)."""
    if has_body(request) and media_type(request) != "application/json":
        raise unsupported_media(request, "application/json")


JsonOnly = Depends(require_json)
