"""Image frames through one map: the front end and the estimator wired together.

`ImageFrontEnd.submit(frame, image)` takes a frame that carries an image instead of
observations (the map pipeline's graph step for such a frame):

1. predict the robot's pose from its last estimate and the frame's odometry,
   with the covariance grown by the odometry noise (map frame);
2. the front end labels the image's features (live landmarks' positions and,
   optionally, covariances from the graph);
3. the estimator processes the frame with those observations;
4. the front end learns what the estimator did (promoted tracks, marginalised
   landmarks).

A refused image (frontend.errors.ImageError) or frame (graph.errors.InvalidFrame)
leaves both the front end and the map unchanged.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from frontend.appearance import rotation_between
from frontend.association import Association, AssociationConfig, Associator
from frontend.association_state import associator_from_doc, associator_to_doc
from frontend.features import Features
from frontend.pipeline import FrontEnd
from graph.factors import odometry_sigmas
from graph.slam import BearingSlam, FrameOutcome
from graph.types import FrameInput, Pose2D
from service.pipeline.covariance import to_map_frame
from service.pipeline.robots import RobotState

__all__ = ["ImageFrameResult", "ImageFrontEnd", "parse_state_doc"]

FloatArray = NDArray[np.float64]

COMPASS_GATE = 3.0
"""Odometry heading sigmas beyond which the visual compass's turn replaces the odometry's
in the prediction (see ImageFrontEnd.predict)."""
COMPASS_MIN_SCORE = 0.6
"""Correlation two consecutive panoramas' signatures need for the compass to count."""


@dataclass(frozen=True)
class ImageFrameResult:
    """The estimator's outcome and the front end's association of one image frame."""

    outcome: FrameOutcome
    association: Association
    timing_ms: dict[str, float]


def parse_state_doc(
    doc: Any, config: AssociationConfig
) -> tuple[Associator, dict[str, tuple[FloatArray, FloatArray]]]:
    """(associator, last pose and covariance per robot) of `ImageFrontEnd.state_doc`'s
    document; ValueError naming the first bad field."""
    if not isinstance(doc, dict):
        raise ValueError("frontend: must be an object with associator and last")
    associator = associator_from_doc(doc.get("associator"), config)
    last_doc = doc.get("last")
    if not isinstance(last_doc, dict):
        raise ValueError("frontend.last: must be an object (robot -> pose, covariance)")
    last: dict[str, tuple[FloatArray, FloatArray]] = {}
    for robot, item in last_doc.items():
        path = f"frontend.last.{robot}"
        try:
            pose = np.asarray(item["pose"], dtype=np.float64)
            cov = np.asarray(item["covariance"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{path}: must be {{pose: [3], covariance: [3][3]}}") from exc
        if pose.shape != (3,) or cov.shape != (3, 3):
            raise ValueError(f"{path}: pose must have 3 numbers, covariance 3x3")
        if not (np.all(np.isfinite(pose)) and np.all(np.isfinite(cov))):
            raise ValueError(f"{path}: must be finite")
        last[robot] = (pose, cov)
    return associator, last


class ImageFrontEnd:
    """One map's front end next to its estimator."""

    def __init__(
        self,
        slam: BearingSlam,
        front_end: FrontEnd,
        *,
        robots: dict[str, RobotState] | None = None,
        landmark_covariances: bool = False,
        compass: bool = True,
    ) -> None:
        """`robots`: the map's per-robot state (each robot's last pose and panorama
        signature live there; default: a dict of its own).
        `landmark_covariances`: gate with the graph's landmark marginals (one joint
        marginal per frame; costly with many landmarks) instead of a default sigma.
        `compass`: let the panoramas' rotation overrule a wrong odometry turn in the
        prediction (see `predict`; False: the odometry alone, e.g. to compare)."""
        self.slam = slam
        self.front_end = front_end
        self.robots: dict[str, RobotState] = {} if robots is None else robots
        self.landmark_covariances = landmark_covariances
        self.compass = compass

    def _robot(self, name: str) -> RobotState:
        return self.robots.setdefault(name, RobotState())

    def last_pose(self, robot: str) -> tuple[FloatArray, FloatArray] | None:
        """The robot's last pose (3,) and (3, 3) map-frame covariance, if the front end
        knows it."""
        state = self.robots.get(robot)
        return None if state is None else state.pose

    def set_associator(self, associator: Associator) -> None:
        # The service's association settings, not the snapshot's: they are not part of a
        # map's config, and an older snapshot's pickled config lacks the newer fields.
        associator.config = self.front_end.associator.config
        self.front_end.associator = associator

    def state_doc(self) -> dict[str, Any]:
        """The front end's state as JSON-ready data (a map export): the associator's
        landmark views and tracks, and each robot's last pose (x, y, theta) with its
        (3, 3) covariance (x, y in the map frame)."""
        return {
            "associator": associator_to_doc(self.front_end.associator),
            "last": {
                name: {"pose": robot.pose[0].tolist(), "covariance": robot.pose[1].tolist()}
                for name, robot in self.robots.items()
                if robot.pose is not None
            },
        }

    def set_state_doc(self, doc: Any) -> None:
        """Put back `state_doc`'s document (checked first: ValueError naming the field;
        nothing changes then). Landmarks the estimator no longer has are dropped at the
        next frame."""
        associator, last = parse_state_doc(doc, self.front_end.associator.config)
        self.front_end.associator = associator
        for robot in self.robots.values():
            robot.pose = None
        for name, pose in last.items():
            self._robot(name).pose = pose

    def note_pose(self, robot: str, pose: Pose2D, covariance_robot: ArrayLike) -> None:
        """The robot's frame went through the estimator by another route (a JSON frame
        with bearing observations): its next image frame is predicted from here.
        `covariance_robot`: (3, 3), x, y in the robot frame (as the estimator reports)."""
        state = self._robot(robot)
        xy_theta = np.array([pose.x, pose.y, pose.theta])
        state.pose = (xy_theta, to_map_frame(np.asarray(covariance_robot), pose.theta))
        # The next image's odometry starts here, not at the last image: no compass for it.
        state.signature = None

    def predict(
        self, frame: FrameInput, *, compass_rad: float | None = None
    ) -> tuple[FloatArray, FloatArray]:
        """Predicted (pose (3,), covariance (3, 3), map frame) of the frame's robot.

        `compass_rad`: the turn since the robot's last image that the panoramas show
        (frontend.appearance.rotation_between). It replaces the odometry's turn when the
        two differ by more than `COMPASS_GATE` of the odometry's heading sigma: the
        odometry is then wrong beyond its noise model (a slipping on-the-spot turn),
        and a prediction that far off would leave the association matching nothing.
        The estimator still gets the frame's odometry as it is."""
        cfg = self.slam.config
        last = self.last_pose(frame.robot)
        if last is None or frame.odometry is None:
            if frame.initial_pose is None:
                raise ValueError(f"robot {frame.robot!r}: first frame needs initial_pose")
            p = frame.initial_pose
            return np.array([p.x, p.y, p.theta]), np.diag(np.square(cfg.initial_pose_sigma))
        pose, cov = last
        odo = frame.odometry
        c, s = math.cos(pose[2]), math.sin(pose[2])
        dxw, dyw = c * odo.dx - s * odo.dy, s * odo.dx + c * odo.dy
        sigmas = odometry_sigmas(odo, cfg)
        turn = odo.dtheta
        if compass_rad is not None:
            gap = math.atan2(math.sin(compass_rad - turn), math.cos(compass_rad - turn))
            if abs(gap) > COMPASS_GATE * sigmas[2]:
                turn = compass_rad
        new = np.array([pose[0] + dxw, pose[1] + dyw, pose[2] + turn])
        new[2] = math.atan2(math.sin(new[2]), math.cos(new[2]))
        jac = np.array([[1.0, 0.0, -dyw], [0.0, 1.0, dxw], [0.0, 0.0, 1.0]])
        q = to_map_frame(np.diag(np.square(sigmas)), pose[2])
        return new, jac @ cov @ jac.T + q

    def submit(
        self,
        frame: FrameInput,
        image: bytes | NDArray[np.uint8] | Features,
        *,
        with_covariance: bool = True,
        signature: NDArray[np.float32] | None = None,
        anchor: tuple[Pose2D, FloatArray] | None = None,
    ) -> ImageFrameResult:
        """Process one frame whose observations come from `image` (its own are ignored).

        `image` may be the image's features already extracted (`front_end.features`,
        e.g. in another thread while the frame was being logged). `signature`: the
        image's appearance signature (frontend.appearance.signature); with the robot's
        previous one it gives the visual compass of `predict`. `anchor`: (pose, (3, 3)
        map-frame covariance) from the place localiser: the robot's chain is anchored
        there (BearingSlam.process), the prediction starts from it, and the robot's
        candidate tracks (rays from poses it no longer believes) are dropped.
        """
        t0 = time.perf_counter()
        feats = image if isinstance(image, Features) else self.front_end.features(image)
        t1 = time.perf_counter()
        compass = None
        state = self._robot(frame.robot)
        previous = state.signature
        if (
            self.compass
            and signature is not None
            and previous is not None
            and previous.shape == signature.shape
        ):
            yaw, score = rotation_between(previous, signature)
            compass = yaw if score >= COMPASS_MIN_SCORE else None
        if anchor is None:
            predicted, cov = self.predict(frame, compass_rad=compass)
        else:
            p = anchor[0]
            predicted, cov = np.array([p.x, p.y, p.theta]), np.asarray(anchor[1], np.float64)
            self.front_end.associator.forget_tracks(frame.robot)
        slam = self.slam
        ids = sorted(slam.landmarks)
        labels = [slam.landmarks[i].label for i in ids]
        xy = list(slam.landmark_positions(ids))
        covs: list[FloatArray | None] = [None] * len(ids)
        if self.landmark_covariances and ids:
            covs = list(slam.landmark_covariances(ids))
        association = self.front_end.observe(
            feats,
            robot=frame.robot,
            predicted_pose=predicted,
            pose_cov=cov,
            landmarks={lb: (p, c) for lb, p, c in zip(labels, xy, covs, strict=True)},
        )
        t2 = time.perf_counter()
        outcome = slam.process(
            replace(frame, observations=association.observations),
            with_covariance=with_covariance,
            anchor=anchor,
        )
        t3 = time.perf_counter()
        pose = np.array([outcome.pose.x, outcome.pose.y, outcome.pose.theta])
        pose_cov = (
            to_map_frame(np.asarray(outcome.covariance), pose[2])
            if outcome.covariance is not None
            else cov
        )
        state.pose = (pose, pose_cov)
        live = {rec.label: rec.id for rec in slam.landmarks.values()}
        touched = set(association.landmark_matches) | set(association.track_matches)
        near = [(lb, i) for lb, i in live.items() if lb in touched]
        xy_near = slam.landmark_positions([i for _, i in near])
        positions = {lb: p for (lb, _), p in zip(near, xy_near, strict=True)}
        archived = (slam.archive.get(i) for i in outcome.marginalised)
        removed = {entry.label for entry in archived if entry is not None}
        self.front_end.commit(
            association,
            pose=pose,
            live_labels=live,
            landmark_xy=positions,
            removed_labels=removed,
        )
        if signature is not None:
            state.signature = signature
        t4 = time.perf_counter()
        return ImageFrameResult(
            outcome=outcome,
            association=association,
            timing_ms={
                "features": 1e3 * (t1 - t0),
                "association": 1e3 * (t2 - t1 + t4 - t3),
                "estimator": 1e3 * (t3 - t2),
                "total": 1e3 * (t4 - t0),
            },
        )
