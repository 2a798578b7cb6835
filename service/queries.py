"""What a map answers besides frames: summary, poses, places, trajectories,
landmarks and coverage, from its session (service.session.MapSession)."""

from __future__ import annotations

from typing import Any

import numpy as np

from service.errors import ServiceError
from service.pipeline.config import slam_config_dict
from service.pipeline.localiser import PlaceLocaliser
from service.session import MapSession
from service.views import attach_frame_stats, coverage_doc, landmarks_doc, pose_doc, trajectory_doc


def _localiser(session: MapSession) -> PlaceLocaliser:
    localiser = session.pipeline.localiser
    assert localiser is not None
    return localiser


def summary(session: MapSession) -> dict[str, Any]:
    """The map's record, estimator parameters, counts, robots and frame timings."""
    frame_ms = session.frame_ms()
    ms = np.asarray(frame_ms) if frame_ms else None
    off_graph = session.pipeline.off_graph_count()
    robots = session.slam.robots
    robots += [r for r in session.pipeline.off_graph_robots() if r not in robots]
    return {
        **session.record.as_dict(),
        "estimator": slam_config_dict(session.slam.config),
        "counts": {
            "frames": session.slam.frame_count + off_graph,
            "off_graph_frames": off_graph,
            "graph_frames": session.slam.graph_frame_count,
            "robots": len(robots),
            "live_landmarks": len(session.slam.landmarks),
            "candidates": session.slam.candidate_count,
            "removals": session.store.removal_count(),
            "graph_variables": session.slam.graph.num_variables,
            "graph_factors": session.slam.graph.num_factors,
            "replay_errors": session.replay_errors,
        },
        "robots": robots,
        "timing_ms": None
        if ms is None
        else {
            "frames": len(ms),
            "mean": float(ms.mean()),
            "p50": float(np.percentile(ms, 50)),
            "p99": float(np.percentile(ms, 99)),
        },
    }


def pose(session: MapSession) -> dict[str, Any]:
    """Latest pose per robot, the graph's or (initialising, lost) the best off-graph
    one: see PlaceLocaliser.robot_poses."""
    localiser, robots = _localiser(session), session.pipeline.robots
    doc = pose_doc(session.slam, session.record.id)
    for name, robot in doc["robots"].items():
        robot["localisation"] = localiser.localisation(name, robots.get(name))
    for name, off in localiser.robot_poses(robots).items():
        if off["pose"] is None and name in doc["robots"]:
            continue
        doc["robots"][name] = off
    return doc


def places(session: MapSession) -> dict[str, Any]:
    """Learnt places and the transitions between them."""
    return {"map_id": session.record.id, **_localiser(session).places_doc()}


def learn_place(session: MapSession, robot: str | None) -> dict[str, Any]:
    """Learn a place at a robot's current pose now (default: the last robot that sent a
    frame); the snapshot taken after it keeps it across restarts."""
    known = session.pipeline.last_accepted()
    if robot is None:
        if not known:
            raise ServiceError(
                409, "no-robot", "No robot yet", "robot: the map has no robot to learn at"
            )
        robot = max(known, key=lambda r: known[r][1])
    if robot not in known:
        raise ServiceError(
            404,
            "unknown-robot",
            "Unknown robot",
            f"robot: map {session.record.id!r} has no robot {robot!r}",
            field="robot",
        )
    if _localiser(session).status(robot) != "tracking":
        raise ServiceError(
            409,
            "not-localised",
            "Robot not localised",
            f"robot: {robot!r} is {_localiser(session).status(robot)}; a place is learnt at a "
            "tracked pose",
            field="robot",
        )
    place = _localiser(session).learn(session.slam, robot, stamp=known[robot][1])
    if place is None:
        raise ServiceError(
            409,
            "too-few-landmarks",
            "Too few landmarks",
            f"robot: fewer than {_localiser(session).localiser.config.places.min_landmarks} mapped "
            f"landmarks lie within {_localiser(session).localiser.config.places.max_depth_m} m of "
            f"{robot!r}",
            field="robot",
        )
    session.snapshot()
    doc = _localiser(session).places_doc()
    return {"map_id": session.record.id, "place": doc["places"][place.id], **doc}


def trajectory(
    session: MapSession, robot: str | None = None, *, stats_every: int = 0
) -> dict[str, list[dict[str, Any]]]:
    """Poses per robot, graph and off-graph frames by seq (`robot`: that robot only);
    `stats_every` > 0: every that many rows carry the frame's statistics."""
    state = None if robot is None else session.pipeline.robots.get(robot)
    if robot not in session.slam.robots and state is not None and state.last is not None:
        rows: dict[str, list[dict[str, Any]]] = {}  # known only to the localiser
    else:
        rows = dict(trajectory_doc(session.slam, session.store, session.record.id, robot))
    session.pipeline.with_off_graph(rows, robot)
    if stats_every > 0:
        labels = session.store.removed_labels()
        labels.update((lid, rec.label) for lid, rec in session.slam.landmarks.items())
        attach_frame_stats(rows, session.store.frame_stats(), labels, every=stats_every)
    return rows


def landmarks(session: MapSession, state: str = "live") -> list[dict[str, Any]]:
    """The live landmarks, or (`state` "archived") those in the archive."""
    if state == "archived":
        return session.store.archived()
    return landmarks_doc(session.slam, session.seed())


def coverage(
    session: MapSession, *, cell_m: float, radius_m: float, removals: int
) -> dict[str, Any]:
    """Coverage grid of the map (see service.views.coverage_doc)."""
    return coverage_doc(
        session.slam,
        session.store,
        session.record.id,
        session.seed(),
        cell_m=cell_m,
        radius_m=radius_m,
        removals=removals,
    )
