"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from api.auth import AUTH_ERRORS, AdminOnly
from api.deps import MetricsDep, ServiceDep

router = APIRouter(tags=["system"])


@router.get("/healthz")
async def healthz() -> dict[str, str]:
    """Liveness: the API process answers (never waits for a worker)."""
    return {"status": "ok"}


@router.get("/readyz", responses={503: {"description": "maps still loading"}})
async def readyz(service: ServiceDep) -> Any:
    """Readiness: 200 once every map is loaded on its worker, else 503. Open to anyone,
    so it tells counts only (process ids and map placement: GET /v1/workers)."""
    workers = service.pool.status()
    body = {
        "ready": service.ready,
        "maps": len(service.list()),
        "workers": len(workers),
        "workers_up": sum(1 for w in workers if w["up"]),
        "maps_loading": sum(w["loading"] for w in workers),
        "worker_restarts": service.pool.restarts,
    }
    return JSONResponse(body, status_code=200 if service.ready else 503)


@router.get("/v1/workers", responses=AUTH_ERRORS, dependencies=[AdminOnly])
async def workers(service: ServiceDep) -> Any:
    """The worker processes (admin key): index, process id, up, generation, maps loading,
    the maps each one runs and their load (requests in flight, time-averaged); the maps
    moved between workers to even out their loads."""
    return {
        "workers": service.pool.status(),
        "worker_restarts": service.pool.restarts,
        "moves": service.pool.moves,
    }


@router.get("/metrics", response_class=Response, responses=AUTH_ERRORS, dependencies=[AdminOnly])
async def metrics(metrics: MetricsDep, service: ServiceDep) -> Response:
    """Prometheus text format: frames, per-stage latency, live landmarks,
    marginalisations, worker restarts."""
    return Response(generate_latest(metrics.registry), media_type=CONTENT_TYPE_LATEST)
