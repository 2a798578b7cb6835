"""Request and response models of REST API v1, with units and conventions per field.

Conventions (DESIGN.md): SI units (metres, radians, seconds); map frame x, y, yaw
theta counter-clockwise from +x (REP-103); a bearing is measured in the robot
frame, counter-clockwise from the robot's forward axis (+x), wrapped to (-pi, pi].
Covariances are row-major nested lists.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from service.exchange import MAP_NAME_MAX_CHARS
from service.frame_results import COV3, Localisation, PoseXYTheta
from service.frame_results import FrameResult as FrameResult  # the frames route's model
from service.keys import Scope
from service.pipeline.config import MapConfig, Mode

_STRICT = ConfigDict(extra="forbid", allow_inf_nan=False)


class FieldError(BaseModel):
    field: str = Field(description="dotted path of the field")
    message: str = Field(description="what is wrong with it")


class Problem(BaseModel):
    """RFC 9457 problem details (media type application/problem+json)."""

    type: str = Field(
        description="URI naming the problem type, e.g. urn:covslam:problem:out-of-order"
    )
    title: str = Field(description="short fixed summary of the problem type")
    status: int = Field(description="HTTP status code")
    detail: str = Field(description="what exactly was wrong: the field (dotted path) and why")
    instance: str | None = Field(None, description="the request path")
    field: str | None = Field(None, description="dotted path of the offending field, if one")
    errors: list[FieldError] | None = Field(
        None, description="every wrong field, when a request fails validation (422)"
    )


# --------------------------------------------------------------------------- maps


class MapCreate(BaseModel):
    """A new map."""

    model_config = _STRICT

    name: str = Field(
        min_length=1, max_length=MAP_NAME_MAX_CHARS, description="human-readable name"
    )
    config: MapConfig = Field(default_factory=MapConfig, description="how the map estimates")
    mode: Mode = Field(
        "mapping",
        description="'mapping' adds landmarks; 'localisation' freezes the map (no new landmarks)",
    )


class MapPatch(BaseModel):
    """Change a map's mode."""

    model_config = _STRICT

    mode: Mode = Field(description="'mapping' or 'localisation' (no new landmarks)")


class MapCounts(BaseModel):
    frames: int = Field(
        description="frames in the map: every acknowledged frame, in the graph or not"
    )
    off_graph_frames: int = Field(
        description="of those, frames the graph did not take (the robot was initialising "
        "or lost): they are in the trajectory with a pose from odometry or the filter"
    )
    graph_frames: int = Field(
        description="frames whose pose is a variable of the graph (in the window, a "
        "keyframe or marginalised since); the others were tracked between them (see the "
        "map config's graph_frame_distance_m) or off the graph"
    )
    robots: int = Field(description="robots that posted frames")
    live_landmarks: int = Field(description="landmarks currently in the graph")
    candidates: int = Field(description="observed labels not yet triangulated")
    removals: int = Field(
        description="removals by the budget so far (a restored landmark removed again counts again)"
    )
    graph_variables: int = Field(description="variables in the factor graph")
    graph_factors: int = Field(description="factors in the factor graph")
    replay_errors: int = Field(description="log frames that failed when the map was reloaded")


class TimingStats(BaseModel):
    frames: int = Field(description="frames the figures cover (the last <= 1000 since load)")
    mean: float = Field(description="mean time per frame in the worker, milliseconds")
    p50: float = Field(description="median time per frame in the worker, milliseconds")
    p99: float = Field(description="99th percentile time per frame in the worker, milliseconds")


class MapPublic(BaseModel):
    """A map's summary."""

    id: str = Field(description="the map's id, used in every other path")
    name: str = Field(description="human-readable name")
    mode: Mode = Field(description="'mapping' or 'localisation' (no new landmarks)")
    config: dict[str, Any] = Field(description="the map config as created (see MapConfig)")
    created: float = Field(description="creation time, seconds since the Unix epoch")
    estimator: dict[str, Any] = Field(
        description="every estimator parameter (SI units: metres, radians)"
    )
    counts: MapCounts = Field(description="sizes of the map and its graph")
    robots: list[str] = Field(description="robot names in the order they joined")
    timing_ms: TimingStats | None = Field(description="worker time per frame; null before any")
    worker: int | None = Field(None, description="index of the worker process owning the map")


class MapBrief(BaseModel):
    id: str = Field(description="the map's id")
    name: str = Field(description="human-readable name")
    mode: Mode = Field(description="'mapping' or 'localisation'")
    config: dict[str, Any] = Field(description="the map config as created (see MapConfig)")
    created: float = Field(description="seconds since the Unix epoch")


# --------------------------------------------------------------------------- frames

# A posted frame's model is service.frame_model.FrameIn: the one validation of a frame
# (posted, in a frame file or in a map's log) and its OpenAPI schema.


# --------------------------------------------------------------------------- queries


class RobotPose(BaseModel):
    seq: int = Field(description="seq of the robot's latest frame")
    stamp: float = Field(description="stamp of that frame, seconds")
    pose: PoseXYTheta | None = Field(
        description="current estimate of the latest pose; for a robot the graph does not "
        "track (initialising, lost) the latest frame's best pose (see the trajectory's "
        "`source`), null while the particle filter has weighed no observation yet"
    )
    covariance: list[list[float]] | None = Field(description=f"{COV3}; null with a null pose")
    localisation: Localisation = Field(description="localisation status of the robot")


class PoseOut(BaseModel):
    map_id: str = Field(description="the map's id")
    robots: dict[str, RobotPose] = Field(description="latest pose per robot name")


class TrajectoryPoint(BaseModel):
    seq: int = Field(description="the frame's seq")
    stamp: float = Field(description="seconds")
    x: float = Field(description="metres, map frame")
    y: float = Field(description="metres, map frame")
    theta: float = Field(description="yaw, radians, counter-clockwise from +x")
    source: Literal["odometry", "filter"] | None = Field(
        None,
        description="only on frames the graph did not take (the robot was initialising or "
        "lost): `odometry` = dead-reckoned from a graph pose (backwards from the frame that "
        "re-anchored the robot, or forwards from its last graph pose while it is lost), "
        "`filter` = the particle filter's estimate",
    )
    # Present only on the poses ?stats_every=N picks (every N-th of a robot, and its latest):
    frame_id: int | None = Field(
        None, description="(stats_every) the frame's position in the map's log (1-based)"
    )
    covariance: list[list[float]] | None = Field(
        None, description=f"(stats_every) {COV3}, as the frame's result reported it then"
    )
    live: int | None = Field(None, description="(stats_every) live landmarks after the frame")
    uncapped: int | None = Field(
        None,
        description="(stats_every) landmarks there would be without the cap: distinct labels "
        "among the landmarks initialised up to this frame (one re-initialised after its "
        "removal counts once)",
    )
    ms: float | None = Field(
        None, description="(stats_every) estimator time for the frame (timing_ms.total), ms"
    )


class TrajectoryOut(BaseModel):
    map_id: str = Field(description="the map's id")
    robots: dict[str, list[TrajectoryPoint]] = Field(
        description="every frame's pose per robot: live poses carry the current estimate, "
        "marginalised poses the last estimate they had"
    )


class ObservedFrom(BaseModel):
    x: float = Field(description="mean robot x the landmark was observed from, metres (E(X))")
    y: float = Field(description="mean robot y the landmark was observed from, metres (E(X))")
    n: int = Field(description="number of observations in the mean")


class _Landmark(BaseModel):
    id: int = Field(description="stable landmark id, never reused")
    label: str = Field(description="the observations' label")
    x: float = Field(description="metres, map frame")
    y: float = Field(description="metres, map frame")
    covariance: list[list[float]] = Field(description="2x2 marginal covariance of (x, y), m²")
    information: float = Field(description="I = 1/var_x + 1/var_y, 1/m²")
    observed_from: ObservedFrom = Field(
        description="running mean E(X) of the robot positions it was observed from (metres)"
    )


class LandmarkOut(_Landmark):
    cluster: int = Field(description="coverage cluster index (see /coverage)")
    first_stamp: float = Field(description="stamp of the first observation, seconds")
    last_stamp: float = Field(description="stamp of the latest observation, seconds")


class ArchivedLandmarkOut(_Landmark):
    """A removed landmark: x, y, covariance and information are its estimate when it was
    removed (of a landmark removed again after a restoration, the better determined of
    that and the one it had been archived with); seen again, it comes back under its id."""

    first_stamp: float = Field(description="stamp of the first observation, seconds")
    last_stamp: float = Field(description="stamp of the latest observation, seconds")
    removed_frame: int = Field(description="estimator frame index of its latest removal")
    removed_stamp: float = Field(description="stamp of that frame, seconds")
    policy: str = Field(description="the policy that removed it")
    reason: str = Field(description="the policy's reason")
    removals: int = Field(description="times it was removed")
    restorations: int = Field(description="times it came back from the archive")


class Cluster(BaseModel):
    index: int = Field(description="cluster index, referenced by LandmarkOut.cluster")
    members: list[int] = Field(description="landmark ids")
    centre: dict[str, float] = Field(
        description="L1 centre of the members' observation positions {x, y}, metres"
    )
    spread: float = Field(description="D = max(I) - min(I) over the members, 1/m²")


class CoverageLandmark(BaseModel):
    id: int = Field(description="landmark id")
    observed_from: ObservedFrom = Field(
        description="running mean E(X) of the robot positions it was observed from (metres)"
    )
    information: float = Field(description="I = 1/var_x + 1/var_y, 1/m²")


class Hole(BaseModel):
    ix: int = Field(description="cell column (along x)")
    iy: int = Field(description="cell row (along y)")
    x: float = Field(description="cell centre x, metres, map frame")
    y: float = Field(description="cell centre y, metres, map frame")


class CoverageGrid(BaseModel):
    cell_m: float = Field(description="cell side, metres")
    radius_m: float = Field(description="'nearby' radius around a cell centre, metres")
    origin: dict[str, float] = Field(description="map-frame corner {x, y} of cell (0, 0), metres")
    width: int = Field(description="cells along x")
    height: int = Field(description="cells along y")
    counts: list[list[int | None]] = Field(
        description="counts[iy][ix]: live landmarks whose mean observation position lies "
        "within radius_m of the cell centre; null for cells no robot visited"
    )
    explored_cells: int = Field(description="cells some pose lies in")
    holes: list[Hole] = Field(description="explored cells with count 0")


class CoverageOut(BaseModel):
    map_id: str = Field(description="the map's id")
    live_landmarks: int = Field(description="landmarks in the graph")
    clusters: list[Cluster] = Field(
        description="k = ceil(live/4) L1 k-means clusters of the observation positions"
    )
    landmarks: list[CoverageLandmark] = Field(
        description="each live landmark's E(X) and information content"
    )
    grid: CoverageGrid = Field(description="coverage grid over the explored area, with holes")
    removal_count: int = Field(
        description="removals so far (a landmark may be removed more than once)"
    )
    removals: list[dict[str, Any]] = Field(
        description="the latest removals with reasons: frame, stamp, landmark_id, label, "
        "x, y (m), observed_from, policy, reason, details"
    )


# --------------------------------------------------------------------------- places


class PlaceLandmarkOut(BaseModel):
    label: str = Field(description="the landmark's label (its appearance signature)")
    landmark_id: int = Field(description="live landmark id when learnt (-1: unknown)")
    bearing: float = Field(description="bearing from the reference pose, radians, robot frame")
    depth: float = Field(description="distance from the reference pose, metres")
    depth_variance: float = Field(description="variance of the depth along the ray, m²")
    uniqueness: float = Field(description="static uniqueness in [0, 1]")
    reliability: float = Field(description="dynamic reliability in [0, 1] (recent matches)")


class PlaceOut(BaseModel):
    id: int = Field(description="place id, stable")
    pose: PoseXYTheta = Field(description="reference pose, map frame")
    robot: str = Field(description="robot that was at the reference pose")
    frame: int = Field(description="map frame count when it was learnt")
    stamp: float = Field(description="stamp of that frame, seconds")
    landmarks: list[PlaceLandmarkOut] = Field(description="the place's landmarks")


class TransitionOut(BaseModel):
    source: int = Field(description="place left")
    target: int = Field(description="place reached next")
    heading: float = Field(description="direction source -> target, radians, map frame")
    distance: float = Field(description="distance between reference positions, metres")
    count: int = Field(description="times this transition was made")


class AppearancePlaceOut(BaseModel):
    id: int = Field(description="appearance place id, stable (a camera map's own series)")
    pose: PoseXYTheta = Field(description="graph pose where the panorama was taken")
    robot: str = Field(description="robot that took it")
    frame: int = Field(description="map frame index of that frame")
    stamp: float = Field(description="stamp of that frame, seconds")


class PlacesOut(BaseModel):
    map_id: str = Field(description="the map's id")
    places: list[PlaceOut] = Field(description="learnt places")
    appearance_places: list[AppearancePlaceOut] = Field(
        default_factory=list,
        description="camera maps: places recognised by the whole panorama's appearance "
        "(yaw-invariant); an image frame's localisation.place is one of these ids",
    )
    transitions: list[TransitionOut] = Field(description="the topological map's edges")


class PlaceLearnIn(BaseModel):
    model_config = _STRICT

    robot: str | None = Field(
        None,
        min_length=1,
        description="robot whose current pose is learnt (default: the last "
        "robot that sent a frame)",
    )


class PlaceLearnt(PlacesOut):
    place: PlaceOut = Field(description="the place just learnt")


# --------------------------------------------------------------------------- API keys


class KeyCreate(BaseModel):
    """A new key for one map."""

    model_config = _STRICT

    scope: Scope = Field(
        description="'read': the map, its queries, export and events; 'write': also "
        "frames and places; 'admin': also mode, delete and the map's keys"
    )


class KeyPublic(BaseModel):
    """A key as listed: never the key itself."""

    id: str = Field(description="the key's id (for DELETE)")
    scope: Scope = Field(description="read, write or admin")
    created: float = Field(description="creation time, Unix seconds")


class KeyCreated(BaseModel):
    """A key just made: `key` is shown this once (only its hash is stored)."""

    id: str = Field(description="the key's id (for DELETE)")
    key: str = Field(description="the secret: send it as 'Authorization: Bearer <key>'")
    scope: Scope = Field(description="read, write or admin")
