"""Dependencies of the routers (built in the app's lifespan, stored on app.state).

They are `async def` on purpose: FastAPI runs plain `def` dependencies in a thread pool,
which would add two thread hand-offs to every request.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Path, Request

from api.metrics import Metrics
from service.maps import MapService


async def get_service(request: Request) -> MapService:
    service: MapService = request.app.state.service
    return service


async def get_metrics(request: Request) -> Metrics:
    metrics: Metrics = request.app.state.metrics
    return metrics


ServiceDep = Annotated[MapService, Depends(get_service)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
MapId = Annotated[str, Path(description="the map's id (from POST /v1/maps)", max_length=64)]
