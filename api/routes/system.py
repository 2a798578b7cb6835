"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from api.deps import MetricsDep, ServiceDep

router = APIRouter(tags=["system"])


@router.get("/healthz")
async def healthz() -> dict[str, str]:
    """Liveness: the API process answers (never waits for a worker)."""
    return {"status": "ok"}


@router.get("/readyz", responses={503: {"description": "maps still loading"}})
async def readyz(service: ServiceDep) -> Any:
    """Readiness: 200 once every map is loaded on its worker, else 503."""
    body = {
        "ready": service.ready,
        "maps": len(service.list()),
        "workers": service.pool.status(),
        "worker_restarts": service.pool.restarts,
    }
    return JSONResponse(body, status_code=200 if service.ready else 503)


@router.get("/metrics", response_class=Response)
async def metrics(metrics: MetricsDep, service: ServiceDep) -> Response:
    """Prometheus text format: frames, per-stage latency, live landmarks,
    marginalisations, worker restarts."""
    return Response(generate_latest(metrics.registry), media_type=CONTENT_TYPE_LATEST)
