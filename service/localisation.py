"""The place localiser wired to one map's estimator (DESIGN.md, frame step 6).

`MapLocalisation.process(slam, frame)` decides per frame whether the graph takes
it: a robot with an initial pose, or one that is tracking, goes through the graph
first and then through its particle filter (which watches for disagreement); a
robot that is initialising or lost only moves its filter, until the filter is
converged and the graph's chain is anchored at its estimate (``relocalised``).
Image frames take the same path through service.camera_localisation (their
observations come from the front end). The whole object pickles; the session keeps
it in its snapshots.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from graph.localiser import INITIALISING, LOST, RELOCALISED, TRACKING, Localiser, LocaliserConfig
from graph.particles import FilterConfig, FilterEstimate
from graph.places import Place
from graph.slam import BearingSlam, FrameOutcome
from graph.snapshot import last_accepted
from graph.types import FrameInput, Pose2D
from service.appearance_places import AppearancePlaces
from service.offgraph import ODOMETRY, OffGraphLog

FloatArray = NDArray[np.float64]


def _rotation(theta: float) -> FloatArray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def to_map_frame(cov_robot: FloatArray, theta: float) -> FloatArray:
    """(3, 3) covariance of (x, y, theta) in the robot frame -> in the map frame."""
    r = _rotation(theta)
    return np.asarray(r @ np.asarray(cov_robot) @ r.T)


def to_robot_frame(cov_map: FloatArray, theta: float) -> FloatArray:
    r = _rotation(theta)
    return np.asarray(r.T @ np.asarray(cov_map) @ r)


@dataclass(frozen=True, slots=True)
class Localised:
    """One frame through the localiser: the graph's outcome (None when the graph did
    not take the frame) and what the frame result reports."""

    robot: str
    seq: int
    stamp: float
    outcome: FrameOutcome | None
    status: str
    place: int | None
    confidence: float | None
    pose: Pose2D
    covariance: FloatArray
    """(3, 3) covariance of (x, y, theta) in the robot frame (as the graph reports it)."""
    learnt: Place | None
    ms: float


MAP_BEARING_SIGMA_FLOOR_RAD = math.radians(1.0)
"""The filter's sensor-sigma floor in a map the graph estimates: its landmarks carry
position error (~5 cm at 3 m is 1 deg) that an observation's own sigma leaves out.
(MRCLAM-6, robot 5 mapping its first 120 s: without the floor the filter, trusting 1 deg
bearings to the graph's landmarks, parted from the graph and sent the robot `lost`.)"""


def map_localiser_config() -> LocaliserConfig:
    """The place localiser's configuration for maps the graph estimates."""
    return LocaliserConfig(filter=FilterConfig(bearing_sigma_floor_rad=MAP_BEARING_SIGMA_FLOOR_RAD))


class MapLocalisation:
    """The map's place localiser, its rng, and each robot's last accepted frame."""

    def __init__(self, seed: int, config: LocaliserConfig | None = None) -> None:
        self.localiser = Localiser(config or map_localiser_config())
        self.rng = np.random.default_rng([seed, 5])
        self.last: dict[str, tuple[int, float]] = {}
        self.off_graph = OffGraphLog()
        """Frames acknowledged while the graph did not take them (see service.offgraph)."""
        self.appearance = AppearancePlaces(
            learn_distance_m=self.localiser.config.places.learn_distance_m
        )
        """Appearance places of a camera map's image frames."""
        self.reported: dict[str, tuple[int | None, float | None]] = {}
        """(place, confidence) that each robot's last frame result reported."""
        self.landmark_matches: dict[str, float] = {}
        """Running average of each camera robot's pose-gated landmark matches per frame
        (service.camera_localisation: a frame far below it is starved)."""

    def __setstate__(self, state: dict[str, Any]) -> None:
        # Snapshots taken before these fields existed lack them.
        state.setdefault("off_graph", OffGraphLog())
        state.setdefault("appearance", AppearancePlaces())
        state.setdefault("reported", {})
        state.setdefault("landmark_matches", {})
        self.__dict__.update(state)

    def localisation(self, robot: str) -> dict[str, Any]:
        """{status, place, confidence} of a robot as its last frame result reported them
        (status as it is now; place and confidence None if no frame since a snapshot
        older than this field)."""
        place, confidence = self.reported.get(robot, (None, None))
        return {"status": self.status(robot), "place": place, "confidence": confidence}

    def last_accepted(self, slam: BearingSlam) -> dict[str, tuple[int, float]]:
        """(seq, stamp) of each robot's last accepted frame, graph or filter only."""
        out = last_accepted(slam)
        out.update(self.last)
        return out

    def status(self, robot: str) -> str:
        track = self.localiser.robots.get(robot)
        return TRACKING if track is None else track.status

    @staticmethod
    def landmark_map(slam: BearingSlam) -> dict[str, FloatArray]:
        return {rec.label: slam.landmark_position(lid) for lid, rec in slam.landmarks.items()}

    def process(
        self, slam: BearingSlam, frame: FrameInput, *, landmark_covariances: bool = True
    ) -> Localised:
        """One frame of one robot (validated by the caller against `last_accepted`).
        `landmark_covariances` False: a place learnt here takes a default landmark
        covariance instead of the graph's joint marginal (a camera map's hundreds of
        landmarks)."""
        track = self.localiser.robots.get(frame.robot)
        feeds_graph = (track is None or track.status in (TRACKING, RELOCALISED)) and (
            frame.robot in slam.robots or frame.initial_pose is not None
        )
        outcome = None
        graph_pose = None
        if feeds_graph:
            outcome = slam.process(frame, with_covariance=True)
            assert outcome.covariance is not None
            p = outcome.pose
            graph_pose = (
                np.array([p.x, p.y, p.theta]),
                to_map_frame(outcome.covariance, p.theta),
            )
        t0 = time.perf_counter()
        prev = self.last.get(frame.robot)
        odo = frame.odometry
        odometry = None if odo is None or prev is None else (odo.dx, odo.dy, odo.dtheta)
        result = self.localiser.step(
            frame.robot,
            odometry=odometry,
            dt_s=0.0 if prev is None else frame.stamp - prev[1],
            labels=[o.label for o in frame.observations],
            bearings_rad=[o.bearing_rad for o in frame.observations],
            sigmas_rad=[o.sigma_rad for o in frame.observations],
            landmarks=self.landmark_map(slam),
            graph_pose=graph_pose,
            rng=self.rng,
            frame=slam.frame_count,
            stamp=frame.stamp,
            covariances=(lambda: self._landmark_covariances(slam))
            if landmark_covariances
            else None,
            ids={rec.label: lid for lid, rec in slam.landmarks.items()},
        )
        ms = 1e3 * (time.perf_counter() - t0)
        est = result.estimate
        if result.anchor:
            anchor = (Pose2D(*(float(v) for v in est.pose_xytheta)), est.covariance)
            outcome = slam.process(frame, with_covariance=True, anchor=anchor)
        self.last[frame.robot] = (frame.seq, frame.stamp)
        self.reported[frame.robot] = (result.place, result.confidence)
        if outcome is not None:
            # In the graph (also the frame that found the robot lost): its graph pose is
            # the one in the trajectory, so it is the one reported.
            assert outcome.covariance is not None
            pose, cov = outcome.pose, np.asarray(outcome.covariance)
            if result.anchor:
                self.off_graph.anchor(frame.robot, seq=frame.seq, odometry=odometry)
            self.off_graph.on_graph(frame.robot, (pose.x, pose.y, pose.theta))
        else:
            pose, cov = self.keep_off_graph(frame, odometry, est)
        return Localised(
            frame.robot,
            frame.seq,
            frame.stamp,
            outcome,
            result.status,
            result.place,
            result.confidence,
            pose,
            cov,
            result.learnt,
            ms,
        )

    def keep_off_graph(
        self,
        frame: FrameInput,
        odometry: tuple[float, float, float] | None,
        est: FilterEstimate,
    ) -> tuple[Pose2D, FloatArray]:
        """A frame the graph did not take (its robot initialising or lost), kept with the
        best pose then available (service.offgraph): that pose, and the filter's
        covariance in the robot frame."""
        x, y, theta = (float(v) for v in est.pose_xytheta)
        kept = self.off_graph.off_graph(
            frame.robot,
            seq=frame.seq,
            stamp=frame.stamp,
            odometry=odometry,
            filter_pose=(x, y, theta),
            converged=est.converged,
        )
        pose = Pose2D(*kept.pose)
        return pose, to_robot_frame(est.covariance, pose.theta)

    def with_off_graph(
        self, rows: dict[str, list[dict[str, Any]]], robot: str | None = None
    ) -> dict[str, list[dict[str, Any]]]:
        """The graph's trajectory rows per robot (`rows`, changed in place and returned)
        with every off-graph frame added, ordered by seq; `robot`: that robot only."""
        for name in self.off_graph.robots():
            if robot is not None and name != robot:
                continue
            graph = rows.get(name, [])
            by_seq = {int(r["seq"]): (r["x"], r["y"], r["theta"]) for r in graph}
            extra = self.off_graph.rows(name, by_seq)
            if extra:
                rows[name] = sorted([*graph, *extra], key=lambda r: int(r["seq"]))
        return rows

    def robot_poses(self) -> dict[str, dict[str, Any]]:
        """Pose documents of the robots the graph does not track now (initialising or
        lost): the latest frame's best pose and the filter's covariance (robot frame);
        pose and covariance null while the filter has not weighed any observation, or
        when the latest frame is a graph frame (the graph's pose then stands)."""
        out: dict[str, dict[str, Any]] = {}
        for name, track in self.localiser.robots.items():
            if track.status not in (INITIALISING, LOST) or name not in self.last:
                continue
            seq, stamp = self.last[name]
            latest = self.off_graph.latest(name)
            est = track.pf.estimate()
            pose: dict[str, float] | None = None
            cov: list[list[float]] | None = None
            known = latest is not None and (latest.source == ODOMETRY or track.pf.w_slow > 0)
            if latest is not None and latest.seq == seq and known:
                x, y, theta = latest.pose
                pose = {"x": x, "y": y, "theta": theta}
                cov = to_robot_frame(est.covariance, theta).tolist()
            out[name] = {
                "seq": seq,
                "stamp": stamp,
                "pose": pose,
                "covariance": cov,
                "localisation": self.localisation(name),
            }
        return out

    @staticmethod
    def _landmark_covariances(slam: BearingSlam) -> dict[str, FloatArray]:
        ids = sorted(slam.landmarks)
        if not ids:
            return {}
        covs = slam.landmark_covariances(ids)
        return {slam.landmarks[i].label: covs[k] for k, i in enumerate(ids)}

    # ------------------------------------------------------------ places
    def learn(self, slam: BearingSlam, robot: str, *, stamp: float) -> Place | None:
        """Learn a place at `robot`'s current pose (the graph's, or the filter's when the
        graph does not track it); None when too few landmarks qualify."""
        landmarks = self.landmark_map(slam)
        track = self.localiser.robots.get(robot)
        if robot in slam.robots and (track is None or track.status == TRACKING):
            p = slam.latest_pose(robot)
            pose = np.array([p.x(), p.y(), p.theta()])
        else:
            assert track is not None
            pose = track.pf.estimate().pose_xytheta
        ids = {rec.label: lid for lid, rec in slam.landmarks.items()}
        return self.localiser.learn(
            robot,
            pose,
            landmarks,
            frame=slam.frame_count,
            stamp=stamp,
            covariances=self._landmark_covariances(slam),
            ids=ids,
        )

    def places_doc(self) -> dict[str, Any]:
        places = self.localiser.places
        return {
            "places": [
                {
                    "id": p.id,
                    "pose": {"x": p.pose.x, "y": p.pose.y, "theta": p.pose.theta},
                    "robot": p.robot,
                    "frame": p.frame,
                    "stamp": p.stamp,
                    "landmarks": [
                        {
                            "label": lm.label,
                            "landmark_id": lm.landmark_id,
                            "bearing": lm.bearing_rad,
                            "depth": lm.depth_m,
                            "depth_variance": lm.depth_var_m2,
                            "uniqueness": lm.uniqueness,
                            "reliability": lm.reliability,
                        }
                        for lm in p.landmarks
                    ],
                }
                for p in places.places
            ],
            "appearance_places": self.appearance.doc(),
            "transitions": [
                {
                    "source": t.source,
                    "target": t.target,
                    "heading": t.heading_rad,
                    "distance": t.distance_m,
                    "count": t.count,
                }
                for t in places.transitions.values()
            ],
        }
