"""The place localiser of one map (DESIGN.md, frame step 6): each robot's particle
filter, the learnt places, and a camera map's appearance places.

A robot with an initial pose, or one that is tracking, goes through the graph first
and then through its particle filter (which watches for disagreement); a robot that
is initialising or lost only moves its filter, until the filter is converged and the
graph's chain is anchored at its estimate (``relocalised``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from graph.localiser import (
    INITIALISING,
    LOST,
    RELOCALISED,
    TRACKING,
    Localiser,
    LocaliserConfig,
    StepResult,
)
from graph.particles import FilterConfig, FilterEstimate
from graph.places import Place
from graph.slam import BearingSlam
from graph.types import BearingObservation
from service.pipeline.appearance import AppearancePlaces
from service.pipeline.covariance import to_robot_frame
from service.pipeline.offgraph import ODOMETRY
from service.pipeline.robots import RobotState

FloatArray = NDArray[np.float64]

MAP_BEARING_SIGMA_FLOOR_RAD = math.radians(1.0)
"""The filter's sensor-sigma floor in a map the graph estimates: its landmarks carry
position error (~5 cm at 3 m is 1 deg) that an observation's own sigma leaves out.
(MRCLAM-6, robot 5 mapping its first 120 s: without the floor the filter, trusting 1 deg
bearings to the graph's landmarks, parted from the graph and sent the robot `lost`.)"""


def map_localiser_config() -> LocaliserConfig:
    """The place localiser's configuration for maps the graph estimates."""
    return LocaliserConfig(filter=FilterConfig(bearing_sigma_floor_rad=MAP_BEARING_SIGMA_FLOOR_RAD))


def landmark_map(slam: BearingSlam) -> dict[str, FloatArray]:
    """label -> (2,) map position of every live landmark."""
    return {rec.label: slam.landmark_position(lid) for lid, rec in slam.landmarks.items()}


def localisation_landmarks(slam: BearingSlam) -> dict[str, FloatArray]:
    """label -> (2,) map position of the landmarks a camera map's filter weighs: the live
    ones (at the graph's estimate) and the archived ones (at their archived estimate),
    whose descriptor views the front end keeps (frontend.association): a robot that
    returns to a place whose landmarks the cap removed still recognises it."""
    out = {
        entry.label: np.array(entry.position, dtype=np.float64)
        for entry in slam.archive
        if entry.id not in slam.landmarks
    }
    out.update(landmark_map(slam))
    return out


def landmark_covariances(slam: BearingSlam) -> dict[str, FloatArray]:
    """label -> (2, 2) marginal covariance of every live landmark (one joint marginal)."""
    ids = sorted(slam.landmarks)
    if not ids:
        return {}
    covs = slam.landmark_covariances(ids)
    return {slam.landmarks[i].label: covs[k] for k, i in enumerate(ids)}


def landmark_ids(slam: BearingSlam) -> dict[str, int]:
    return {rec.label: lid for lid, rec in slam.landmarks.items()}


class PlaceLocaliser:
    """The map's place localiser, its rng, and a camera map's appearance places."""

    def __init__(self, seed: int, config: LocaliserConfig | None = None) -> None:
        self.localiser = Localiser(config or map_localiser_config())
        self.rng = np.random.default_rng([seed, 5])
        self.appearance = AppearancePlaces(
            learn_distance_m=self.localiser.config.places.learn_distance_m
        )
        """Appearance places of a camera map's image frames."""

    def status(self, robot: str) -> str:
        track = self.localiser.robots.get(robot)
        return TRACKING if track is None else track.status

    def feeds_graph(self, robot: str) -> bool:
        """Whether the robot's filter lets the graph take its frames (it is tracking,
        relocalised, or has no filter yet)."""
        return self.status(robot) in (TRACKING, RELOCALISED)

    def step(
        self,
        slam: BearingSlam,
        robot: str,
        *,
        odometry: Sequence[float] | None,
        dt_s: float,
        stamp: float,
        weighed: Sequence[BearingObservation],
        quality: Sequence[float] | None,
        graph_pose: tuple[FloatArray, FloatArray] | None,
        landmarks: Mapping[str, FloatArray],
        covariances: bool,
        hints: Sequence[tuple[FloatArray, float]] | None = None,
        verify: Callable[[FilterEstimate], bool] | None = None,
    ) -> StepResult:
        """The robot's filter over one frame: `weighed` are the bearings it weighs
        (`quality`: each one's match quality), `graph_pose` the graph's (pose (3,),
        (3, 3) map-frame covariance) for the frame or None. `covariances`: a place
        learnt here takes the graph's joint landmark marginal (else a default)."""
        return self.localiser.step(
            robot,
            odometry=odometry,
            dt_s=dt_s,
            labels=[o.label for o in weighed],
            bearings_rad=[o.bearing_rad for o in weighed],
            sigmas_rad=[o.sigma_rad for o in weighed],
            quality=quality,
            landmarks=landmarks,
            graph_pose=graph_pose,
            rng=self.rng,
            frame=slam.frame_count,
            stamp=stamp,
            covariances=(lambda: landmark_covariances(slam)) if covariances else None,
            ids=landmark_ids(slam),
            hints=hints,
            verify=verify,
        )

    def robot_poses(self, robots: Mapping[str, RobotState]) -> dict[str, dict[str, Any]]:
        """Pose documents of the robots the graph does not track now (initialising or
        lost): the latest frame's best pose and the filter's covariance (robot frame);
        pose and covariance null while the filter has not weighed any observation, or
        when the latest frame is a graph frame (the graph's pose then stands)."""
        out: dict[str, dict[str, Any]] = {}
        for name, track in self.localiser.robots.items():
            state = robots.get(name)
            if track.status not in (INITIALISING, LOST) or state is None or state.last is None:
                continue
            seq, stamp = state.last
            latest = state.off_graph.latest()
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
                "localisation": self.localisation(name, state),
            }
        return out

    def localisation(self, robot: str, state: RobotState | None) -> dict[str, Any]:
        """{status, place, confidence} of a robot as its last frame result reported them
        (status as it is now; place and confidence None if no frame yet)."""
        place, confidence = (None, None) if state is None else state.reported
        return {"status": self.status(robot), "place": place, "confidence": confidence}

    def learn(self, slam: BearingSlam, robot: str, *, stamp: float) -> Place | None:
        """Learn a place at `robot`'s current pose (the graph's, or the filter's when the
        graph does not track it); None when too few landmarks qualify."""
        track = self.localiser.robots.get(robot)
        if robot in slam.robots and (track is None or track.status == TRACKING):
            p = slam.latest_pose(robot)
            pose = np.array([p.x(), p.y(), p.theta()])
        else:
            assert track is not None
            pose = track.pf.estimate().pose_xytheta
        return self.localiser.learn(
            robot,
            pose,
            landmark_map(slam),
            frame=slam.frame_count,
            stamp=stamp,
            covariances=landmark_covariances(slam),
            ids=landmark_ids(slam),
        )

    def places_version(self) -> tuple[int, ...]:
        """Changes whenever `places_doc` would: places are only added, and a transition
        is only added or counted up (so a published places document can be kept until
        this changes instead of being rebuilt for every frame)."""
        places = self.localiser.places
        return (
            id(places),
            len(places.places),
            len(places.transitions),
            sum(t.count for t in places.transitions.values()),
            id(self.appearance),
            len(self.appearance.places),
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
