"""What a map answers besides frames, as typed requests (service.requests.MapRequest):
its summary, poses, trajectories, landmarks, coverage and places, and the two changes a
client makes besides frames (the mode, learning a place).

A query is one frozen dataclass: its fields are the query's parameters, `answer(session)`
computes the reply from the map's session (service.session.MapSession) in the worker
process that owns the map, and its type parameter is the reply's type. The API asks
``await service.query(map_id, Pose())``; code in process calls ``Pose().answer(session)``.
Adding a query: a class here and the route that asks it. A query that the map's
published view (service.published) can answer says how in `from_view`: the API process
then answers it without waiting for the worker.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from graph.trajectory import with_final_rows
from service.errors import ServiceError, unknown_robot
from service.pipeline.config import Mode
from service.pipeline.coverage import coverage_grid
from service.pipeline.documents import (
    clusters_doc,
    landmark_table,
    landmarks_doc,
    pose_doc,
    trajectory_rows,
)
from service.pipeline.localiser import PlaceLocaliser
from service.requests import Doc, MapRequest
from service.session import MapSession
from service.store import FrameFigures

if TYPE_CHECKING:
    from service.published import MapView
    from service.store import Store


def _localiser(session: MapSession) -> PlaceLocaliser:
    localiser = session.pipeline.localiser
    assert localiser is not None
    return localiser


@dataclass(frozen=True)
class Summary(MapRequest[Doc]):
    """The map's record, estimator parameters, counts, robots and frame timings."""

    def answer(self, session: MapSession) -> Doc:
        frame_ms = session.frame_ms()
        ms = frame_ms if len(frame_ms) else None
        off_graph = session.pipeline.off_graph_count()
        robots = session.slam.robots
        robots += [r for r in session.pipeline.off_graph_robots() if r not in robots]
        return {
            **session.record.as_dict(),
            "estimator": session.estimator_doc(),
            "counts": {
                "frames": session.slam.frame_count + off_graph,
                "off_graph_frames": off_graph,
                "graph_frames": session.slam.graph_frame_count,
                "robots": len(robots),
                "live_landmarks": len(session.slam.landmarks),
                "candidates": session.slam.candidate_count,
                "removals": session.removal_count(),
                "graph_variables": session.slam.graph.num_variables,
                "graph_factors": session.slam.graph.num_factors,
                "replay_errors": session.replay_errors,
            },
            "robots": robots,
            "timing_ms": None if ms is None else _timing(ms),
        }

    def from_view(self, view: MapView, store: Store) -> Doc:
        return view.summary


def _timing(ms: np.ndarray) -> Doc:
    """Frames, mean, p50 and p99 of frame times, ms (a summary is published with every
    frame: one sort, and the percentiles as numpy's default `percentile` takes them,
    without its overhead)."""
    ordered = np.sort(ms)
    return {
        "frames": len(ms),
        "mean": float(ms.mean()),
        "p50": _percentile(ordered, 50),
        "p99": _percentile(ordered, 99),
    }


def _percentile(ordered: np.ndarray, q: float) -> float:
    """`numpy.percentile(ordered, q)` (linear) of (N,) sorted values, N >= 1."""
    position = (len(ordered) - 1) * q / 100
    lo = int(position)
    a, b = float(ordered[lo]), float(ordered[min(lo + 1, len(ordered) - 1)])
    t = position - lo
    return b - (b - a) * (1 - t) if t >= 0.5 else a + (b - a) * t  # numpy's lerp


@dataclass(frozen=True)
class SetMode(MapRequest[Doc]):
    """Switch between mapping and localisation (a frozen map: no new landmarks); the
    map's summary."""

    mode: Mode

    def answer(self, session: MapSession) -> Doc:
        session.set_mode(self.mode)
        return Summary().answer(session)


@dataclass(frozen=True)
class Pose(MapRequest[Doc]):
    """Latest pose per robot, the graph's or (initialising, lost) the best off-graph
    one: see PlaceLocaliser.robot_poses."""

    def answer(self, session: MapSession) -> Doc:
        return pose_answer(session)

    def from_view(self, view: MapView, store: Store) -> Doc:
        return view.pose

    def view_behind(self, view: MapView) -> bool:
        return view.poses_log_id < view.log_id


def pose_answer(session: MapSession, only: str | None = None) -> Doc:
    """`Pose`'s answer; `only`: with that robot's entry only (if it has one)."""
    localiser, robots = _localiser(session), session.pipeline.robots
    doc = pose_doc(session.slam, session.record.id, only)
    for name, robot in doc["robots"].items():
        robot["localisation"] = localiser.localisation(name, robots.get(name))
    for name, off in localiser.robot_poses(robots).items():
        if (only is not None and name != only) or (off["pose"] is None and name in doc["robots"]):
            continue
        doc["robots"][name] = off
    return doc


@dataclass(frozen=True)
class Places(MapRequest[Doc]):
    """Learnt places and the transitions between them."""

    def answer(self, session: MapSession) -> Doc:
        return {"map_id": session.record.id, **_localiser(session).places_doc()}

    def from_view(self, view: MapView, store: Store) -> Doc | None:
        return view.places


@dataclass(frozen=True)
class LearnPlace(MapRequest[Doc]):
    """Learn a place at a robot's current pose now (default: the last robot that sent a
    frame); the snapshot taken after it keeps it across restarts."""

    robot: str | None = None

    def answer(self, session: MapSession) -> Doc:
        known = session.pipeline.last_accepted()
        robot = self.robot
        if robot is None:
            if not known:
                raise ServiceError(
                    409, "no-robot", "No robot yet", "robot: the map has no robot to learn at"
                )
            robot = max(known, key=lambda r: known[r][1])
        if robot not in known:
            raise unknown_robot(session.record.id, robot)
        localiser = _localiser(session)
        if localiser.status(robot) != "tracking":
            raise ServiceError(
                409,
                "not-localised",
                "Robot not localised",
                f"robot: {robot!r} is {localiser.status(robot)}; a place is learnt at a "
                "tracked pose",
                field="robot",
            )
        place = localiser.learn(session.slam, robot, stamp=known[robot][1])
        if place is None:
            places = localiser.localiser.config.places
            raise ServiceError(
                409,
                "too-few-landmarks",
                "Too few landmarks",
                f"robot: fewer than {places.min_landmarks} mapped landmarks lie within "
                f"{places.max_depth_m} m of {robot!r}",
                field="robot",
            )
        session.snapshot()
        doc = localiser.places_doc()
        return {"map_id": session.record.id, "place": doc["places"][place.id], **doc}


@dataclass(frozen=True)
class Trajectory(MapRequest[dict[str, list[Doc]]]):
    """Poses per robot, graph and off-graph frames by seq (`robot`: that robot only);
    `stats_every` > 0: every that many rows carry the frame's statistics."""

    robot: str | None = None
    stats_every: int = 0
    view_reads_store = True

    def answer(self, session: MapSession) -> dict[str, list[Doc]]:
        robot = self.robot
        state = None if robot is None else session.pipeline.robots.get(robot)
        if robot not in session.slam.robots and state is not None and state.last is not None:
            rows: dict[str, list[Doc]] = {}  # known only to the localiser
        else:
            if robot is not None and robot not in session.slam.robots:
                raise unknown_robot(session.record.id, robot, " (GET /pose lists its robots)")
            final = session.store.poses(robot)  # the estimator holds the newer rows
            rows = {
                name: trajectory_rows(with_final_rows(final.get(name), held))
                for name, held in session.slam.trajectory(robot).items()
            }
        session.pipeline.with_off_graph(rows, robot)
        if self.stats_every > 0:
            labels = session.store.removed_labels()
            labels.update((lid, rec.label) for lid, rec in session.slam.landmarks.items())
            attach_frame_stats(rows, session.store.frame_stats(), labels, every=self.stats_every)
        return rows

    def view_behind(self, view: MapView) -> bool:
        return view.held_log_id < view.log_id

    def from_view(self, view: MapView, store: Store) -> dict[str, list[Doc]] | None:
        robot = self.robot
        if self.stats_every or view.held is None or (robot is not None and robot not in view.held):
            return None  # frame statistics, off-graph rows, an unknown robot: the worker's
        final = store.read_poses(view.map_id, robot)
        return {
            name: trajectory_rows(with_final_rows(final.get(name), held))
            for name, held in view.held.items()
            if robot is None or name == robot
        }


@dataclass(frozen=True)
class Landmarks(MapRequest[list[Doc]]):
    """The live landmarks, or (`state` "archived") those in the archive."""

    state: Literal["live", "archived"] = "live"

    def answer(self, session: MapSession) -> list[Doc]:
        if self.state == "archived":
            return session.store.archived()
        return landmarks_doc(session.slam, session.seed())

    def from_view(self, view: MapView, store: Store) -> list[Doc] | None:
        return view.landmarks if self.state == "live" else None

    def view_behind(self, view: MapView) -> bool:
        return view.landmarks_log_id < view.log_id


@dataclass(frozen=True)
class Coverage(MapRequest[Doc]):
    """Coverage clusters with spreads, each live landmark's E(X) and information, the
    coverage grid (service.pipeline.coverage) over every pose of the map, and the latest
    `removals` of the removal log."""

    cell_m: float = 1.0
    radius_m: float = 2.0
    removals: int = 200

    def answer(self, session: MapSession) -> Doc:
        slam, store = session.slam, session.store
        table, _ = landmark_table(slam)
        _, clusters = clusters_doc(table, session.seed())
        positions = [store.pose_positions(), *(r[:, 2:4] for r in slam.trajectory().values())]
        assert table.information is not None
        return {
            "map_id": session.record.id,
            "live_landmarks": len(table),
            "clusters": clusters["clusters"] if clusters else [],
            "landmarks": [
                {
                    "id": int(lid),
                    "observed_from": {
                        "x": float(table.observed_from[i, 0]),
                        "y": float(table.observed_from[i, 1]),
                        "n": int(table.counts[i]),
                    },
                    "information": float(table.information[i]),
                }
                for i, lid in enumerate(table.ids)
            ],
            "grid": coverage_grid(
                np.concatenate(positions),
                table.observed_from,
                cell_m=self.cell_m,
                radius_m=self.radius_m,
            ),
            "removal_count": store.removal_count(),
            "removals": store.removals(limit=self.removals),
        }


def attach_frame_stats(
    robots: dict[str, list[dict[str, Any]]],
    stats: list[FrameFigures],
    labels: dict[int, str],
    *,
    every: int,
) -> None:
    """Add frame figures to every `every`-th pose of each robot and to its latest, in place.

    `stats` are `MapStore.frame_stats` rows in log order; `labels` maps every landmark
    id the map ever had to its label. Each chosen trajectory row gains ``frame_id``,
    ``covariance`` (3x3, as the frame's result reported it when the frame was
    processed), ``live``, ``ms`` and ``uncapped``: the landmarks there would be without
    the cap, i.e. the distinct labels among the landmarks initialised up to that frame
    (one seen again after its removal comes back under its id; re-triangulated under a
    new id instead, with SlamConfig.restore_archived off, it still counts once).
    """
    if every <= 0 or not stats:
        return
    seen_ids: set[int] = set()
    seen_labels: set[str] = set()
    uncapped = []
    for row in stats:
        # a landmark removed by the frame that initialised it is only in `marginalised`
        for lid in (*row.added, *row.marginalised):
            if lid not in seen_ids:
                seen_ids.add(lid)
                seen_labels.add(labels.get(lid, f"id:{lid}"))
        uncapped.append(len(seen_labels))
    by_key = {(row.robot, row.seq): k for k, row in enumerate(stats)}
    for name, rows in robots.items():
        for i, point in enumerate(rows):
            if i % every and i != len(rows) - 1:
                continue
            k = by_key.get((name, int(point["seq"])))
            if k is None:
                continue
            row = stats[k]
            point["frame_id"] = row.frame_id
            cov = row.covariance_json
            point["covariance"] = None if cov is None else json.loads(cov)
            point["live"] = row.live
            point["uncapped"] = uncapped[k]
            point["ms"] = row.total_ms
