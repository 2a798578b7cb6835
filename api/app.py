"""The FastAPI application: REST API v1 of covslam.

`create_app(settings)` builds the app; the map service (catalogue + worker pool)
is started in the lifespan, never at import.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline

from api import errors
from api.docs import DOCS_ASSETS, DocsPolicy
from api.metrics import Metrics
from api.routes import events, frames, keys, maps, places, queries, system
from service.frame_model import FrameIn
from service.maps import MapService
from service.settings import Settings, get_settings

DESCRIPTION = """Bearing-only SLAM as a web service.

Conventions: SI units (metres, radians, seconds). Map frame: x, y, yaw theta
counter-clockwise from +x (REP-103). A bearing is measured in the robot frame,
counter-clockwise from the robot's forward axis (+x), wrapped to (-pi, pi].
Odometry is the motion since the robot's previous frame, in the previous robot frame.
Errors are RFC 9457 problem+json. The dashboard is served at /dashboard/.

Authentication: `Authorization: Bearer <key>` (the admin key, or a map's key of scope
read, write or admin; see docs/deployment.md). /healthz and /readyz are open.
"""

DOCUMENTED = (maps, keys, frames, queries, events, places, system)
"""The routers in the order the OpenAPI document lists their paths."""

DASHBOARD_DIR = Path(__file__).resolve().parent / "dashboard"
"""The dashboard's static files (plain HTML, CSS and JavaScript modules; package data)."""


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()
    settings.check_bind()
    metrics = Metrics()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        service = MapService(settings, on_worker_restart=lambda _: metrics.restarts.inc())
        app.state.service = service
        await service.start()
        try:
            yield
        finally:
            await service.stop()

    app = FastAPIOffline(  # /docs and /redoc with local assets (api/docs.py)
        static_url=DOCS_ASSETS,
        title="covslam",
        version="1",
        description=DESCRIPTION,
        lifespan=lifespan,
    )
    app.state.metrics = metrics
    app.state.settings = settings
    errors.install(app)
    app.add_middleware(frames.FramesLane)  # inside BodyLimit: the body limits apply
    app.add_middleware(
        errors.BodyLimit,
        max_bytes=settings.api.max_body_bytes,
        max_import_bytes=settings.api.max_import_bytes,
        max_image_frame_bytes=settings.api.max_image_bytes + (1 << 20),
    )
    app.add_middleware(DocsPolicy)
    # Routing tries the routers in order, and frames are most requests: theirs goes first.
    # The OpenAPI document keeps the order below (see `openapi`).
    for module in (frames, *(m for m in DOCUMENTED if m is not frames)):
        app.include_router(module.router)
    app.mount("/dashboard", StaticFiles(directory=DASHBOARD_DIR, html=True), name="dashboard")

    default_openapi = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = default_openapi()
            paths = schema["paths"]
            order = [r.path for m in DOCUMENTED for r in m.router.routes]
            schema["paths"] = {p: paths[p] for p in dict.fromkeys(order) if p in paths} | paths
            frame = FrameIn.model_json_schema(ref_template="#/components/schemas/{model}")
            components = schema.setdefault("components", {}).setdefault("schemas", {})
            components.update(frame.pop("$defs", {}))
            components["FrameIn"] = frame
            errors.declare_problem_responses(schema)
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
    return app
