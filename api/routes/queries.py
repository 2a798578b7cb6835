"""Read the map: latest poses, trajectories (JSON or TUM), landmarks, coverage."""

from __future__ import annotations

import io
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Query, Response

from api.auth import AUTH_ERRORS, MapRead
from api.deps import MapId, ServiceDep
from api.models import (
    ArchivedLandmarkOut,
    CoverageOut,
    LandmarkOut,
    PoseOut,
    Problem,
    TrajectoryOut,
)
from service import tum
from service.errors import ServiceError
from service.queries import Coverage, Landmarks, Pose, Trajectory

router = APIRouter(prefix="/v1/maps/{map_id}", tags=["map"], dependencies=[MapRead])

_ERRORS: dict[int | str, dict[str, Any]] = {
    **AUTH_ERRORS,
    404: {"model": Problem, "description": "unknown map or robot"},
    503: {"model": Problem, "description": "the map's worker is restarting; see Retry-After"},
}


@router.get("/pose", response_model=PoseOut, responses=_ERRORS)
async def get_pose(map_id: MapId, service: ServiceDep) -> Any:
    """Latest pose of each robot with its 3x3 covariance and localisation status."""
    return await service.query(map_id, Pose())


@router.get(
    "/trajectory",
    response_model=TrajectoryOut,
    response_model_exclude_none=True,
    responses={
        **_ERRORS,
        200: {
            "content": {"text/plain": {"schema": {"type": "string"}}},
            "description": "JSON, or with format=tum one robot's TUM text: "
            "`stamp x y z qx qy qz qw` per line (z = qx = qy = 0, qz = sin(theta/2), "
            "qw = cos(theta/2); seconds, metres) as evo reads it",
        },
    },
)
async def get_trajectory(
    map_id: MapId,
    service: ServiceDep,
    robot: Annotated[str | None, Query(description="one robot only (required for tum)")] = None,
    format: Annotated[Literal["json", "tum"], Query(description="json or tum")] = "json",
    stats_every: Annotated[
        int,
        Query(
            ge=0,
            le=1_000_000,
            description="json: add frame_id, covariance, live, uncapped and ms to every "
            "n-th pose of each robot and to its latest (0 = none)",
        ),
    ] = 0,
) -> Any:
    """Every frame's pose per robot `[{seq, stamp, x, y, theta}]`; with `stats_every`
    also what the frame's result reported (pose covariance at the time, live and uncapped
    landmark counts, estimator ms): the dashboard's ellipses and time plots."""
    if format == "tum" and robot is None:
        raise ServiceError(
            422,
            "invalid-request",
            "Invalid request",
            "robot: format=tum needs one robot (?robot=NAME)",
            field="robot",
        )
    stats = stats_every if format == "json" else 0
    rows = await service.query(map_id, Trajectory(robot, stats))
    if format == "tum":
        assert robot is not None
        return Response(tum_text(rows[robot]), media_type="text/plain; charset=utf-8")
    return {"map_id": map_id, "robots": rows}


@router.get(
    "/landmarks",
    response_model=list[LandmarkOut] | list[ArchivedLandmarkOut],
    responses=_ERRORS,
)
async def get_landmarks(
    map_id: MapId,
    service: ServiceDep,
    state: Annotated[
        Literal["live", "archived"],
        Query(description="live: the graph's landmarks; archived: those the budget removed"),
    ] = "live",
) -> Any:
    """Live landmarks with marginal covariance, information content, mean observation
    position E(X) and coverage cluster; with `state=archived`, the landmarks the budget
    removed that have not come back (their last estimate and covariance, E(X), count, the
    latest removal's reason). Seen again, an archived landmark comes back under its id
    (event `landmark_restored`)."""
    return await service.query(map_id, Landmarks(state))


@router.get("/coverage", response_model=CoverageOut, responses=_ERRORS)
async def get_coverage(
    map_id: MapId,
    service: ServiceDep,
    cell_m: Annotated[float, Query(gt=0.05, le=100, description="grid cell side, metres")] = 1.0,
    radius_m: Annotated[
        float | None, Query(gt=0, le=1000, description="'nearby' radius, metres (2 cells)")
    ] = None,
    removals: Annotated[int, Query(ge=0, le=100_000, description="latest removals listed")] = 200,
) -> Any:
    """Coverage clusters with spreads D, each landmark's E(X) and information, the
    coverage grid with its holes, and the removal log with reasons."""
    radius = radius_m if radius_m is not None else 2.0 * cell_m
    return await service.query(map_id, Coverage(cell_m, radius, removals))


def tum_text(rows: list[dict[str, float]]) -> str:
    """TUM lines ``stamp x y 0 0 0 qz qw`` of trajectory rows (as `Trajectory` answers)."""
    stamps = np.array([r["stamp"] for r in rows], dtype=np.float64)
    poses = np.array([[r["x"], r["y"], r["theta"]] for r in rows], dtype=np.float64)
    buf = io.StringIO()
    trajectory = tum.Trajectory.from_poses(stamps, poses.reshape(-1, 3))
    tum.write_tum(buf, trajectory)  # type: ignore[arg-type]
    return buf.getvalue()
