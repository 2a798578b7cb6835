"""One map in process: `MapPipeline.step(frame, *, image=None) -> FrameStep`.

A frame's way (DESIGN.md, "One frame's way through the system", steps 2-6), over
named collaborators:

- the **front end** (`ImageFrontEnd`, a camera map only) turns an image frame's
  features into bearing observations: association with the live landmarks, gated by
  the pose predicted from the robot's last one; a JSON frame's observations are given;
- the **estimator** (graph.slam.BearingSlam, its landmark **budget policy** inside)
  takes the frame when the localiser lets the graph track the robot;
- the **localiser** (`PlaceLocaliser`) steps the robot's particle filter on what the
  frame saw, watches it for disagreement with the graph (``lost``), and, once the
  filter of a robot the graph does not track has converged, anchors the robot's chain
  at its estimate (``relocalised``): the estimator then takes the frame from there;
- each robot's `RobotState` keeps what the pipeline knows of it between frames; a
  frame the graph does not take is kept off the graph with its best pose
  (service.pipeline.offgraph).

What the filter weighs: a JSON frame's observations. An image frame of a tracked
robot: up to `MAX_FILTER_OBSERVATIONS` of its pose-gated landmark matches -- unless the
frame is *starved* (its matches fall far below the robot's running average: what a
robot carried elsewhere sees, its prediction being wrong), when the features matched to
the landmarks by descriptor alone are weighed instead, which do not depend on the
believed pose. An image frame of a robot the graph does not track: those pose-free
matches, and the filter's injection proposals come from the appearance places that
recognition ranks highest. Before such a robot is relocalised, the pose-gated
association run from the filter's estimate must match enough landmarks (look-alike
posters of an unmapped room can draw the filter to a pose their pose-free matches fit
by chance); if not, the filter searches afresh. In a camera map the filter's landmarks
are the live ones and the archived ones (at their archived estimates, matched by the
views the front end archived with them): a cap removes landmarks from the graph, not
from what a returning robot can recognise.

The observations a frame is recorded with (a map export carries them): the
association's for an image frame the graph took, the pose-free matches the filter
weighed otherwise, the given ones for a JSON frame.

Without a localiser (an offline replay) every frame goes to the estimator.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from frontend.appearance import AppearanceMatch
from frontend.association import Association
from frontend.features import Features
from graph.localiser import StepResult
from graph.particles import FilterEstimate
from graph.places import Place
from graph.slam import BearingSlam, FrameOutcome
from graph.snapshot import last_accepted
from graph.types import BearingObservation, FrameInput, Pose2D
from service.pipeline.covariance import to_map_frame, to_robot_frame
from service.pipeline.images import ImageFrontEnd
from service.pipeline.localiser import PlaceLocaliser, landmark_map, localisation_landmarks
from service.pipeline.robots import RobotState

__all__ = ["FrameStep", "ImageFeatures", "MapPipeline"]

FloatArray = NDArray[np.float64]
Pose = tuple[float, float, float]

MAX_FILTER_OBSERVATIONS = 64
"""Most bearings one image frame gives the filter (spread over the panorama): a frame
matches 100+ landmarks, and the filter's cost grows with them while 64 already pin the
pose."""
STARVED_SHARE = 0.3
"""A frame is starved when its pose-gated landmark matches fall below this share of
the robot's running average..."""
STARVED_MIN_AVERAGE = 15.0
"""... provided that average is at least this (a robot that usually sees few landmarks
says nothing by seeing few), or `STARVED_LIVE_SHARE` of the map's live landmarks if that
is fewer..."""
STARVED_LIVE_SHARE = 0.3
"""... (a landmark cap keeps few live, and the pose-gated association matches live
landmarks only: a robot that usually matches 12 of a cap's 30 sees much of what the map
holds; at cap 30 the average stays near 12 and a kidnap went unnoticed)..."""
STARVED_FLOOR = 8.0
"""... but never below this: a robot that usually matches a handful of landmarks sees
none by chance now and then (Poisson, mean 8: 2 or fewer in 1.4 % of frames)."""
AVERAGE_RATE = 0.1
"""Weight of a frame in the running average of landmark matches."""
TOP_HINTS = 3
"""Appearance places the injection proposal draws around."""
VERIFY_MIN_MATCHES = 40
"""A searching robot is relocalised only if the pose-gated association, run from the
filter's converged estimate, matches at least this many landmarks... (In an unmapped
room the pose-free matches are look-alikes, and the filter can converge on a pose they
happen to fit: rendered rooms, 2 seeds, such poses 4-8 m off had 11-18 gated matches,
true poses 0-1 m from the mapped path 142-177. Without the check 3 of 4 robots in the
unmapped room were relocalised 4-6 m off.)"""
VERIFY_SHARE = 0.5
"""... and at least this share of the frame's pose-free matches."""


@dataclass(frozen=True)
class ImageFeatures:
    """An image frame's features and its panorama's appearance signature (None: no
    visual compass, no appearance places)."""

    features: Features
    signature: NDArray[np.float32] | None = None


@dataclass(frozen=True)
class FrameStep:
    """One frame through the pipeline."""

    robot: str
    seq: int
    stamp: float
    outcome: FrameOutcome | None
    """The estimator's outcome; None when the graph did not take the frame."""
    status: str
    place: int | None
    confidence: float | None
    pose: Pose2D
    covariance: FloatArray | None
    """(3, 3) covariance of (x, y, theta) in the robot frame (as the graph reports it;
    None from an estimator asked for no pose marginal)."""
    learnt: Place | None
    observations: tuple[BearingObservation, ...]
    """What the frame is recorded with (see the module docstring)."""
    timing_ms: dict[str, float]
    """localise (wall ms of everything but the front end's association and the
    estimator); an image frame also: association (wall ms of those), localise_cpu (this
    thread's CPU ms of `localise`)."""


@dataclass
class _GraphStep:
    outcome: FrameOutcome
    association: Association | None


@dataclass
class _FilterInput:
    """What the filter weighs of one frame, and the map it weighs it against."""

    weighed: Sequence[BearingObservation]
    quality: Sequence[float] | None = None
    hints: Sequence[tuple[FloatArray, float]] | None = None
    verify: Callable[[FilterEstimate], bool] | None = None
    landmarks: dict[str, FloatArray] = field(default_factory=dict)
    found: AppearanceMatch | None = None
    """The image's appearance match against the map's appearance places."""


class _Clock:
    """A frame's wall and CPU time, and the share of it in the estimator's graph steps
    (with an image frame's association)."""

    def __init__(self, *, image: bool) -> None:
        self.image = image
        self.wall0, self.cpu0 = time.perf_counter(), time.thread_time()
        self.graph_wall = self.graph_cpu = 0.0

    @contextmanager
    def graph(self) -> Iterator[None]:
        w, c = time.perf_counter(), time.thread_time()
        try:
            yield
        finally:
            self.graph_wall += time.perf_counter() - w
            self.graph_cpu += time.thread_time() - c

    def timing_ms(self, *, image: bool) -> dict[str, float]:
        wall = 1e3 * (time.perf_counter() - self.wall0 - self.graph_wall)
        if not image:
            return {"localise": wall}
        cpu = 1e3 * (time.thread_time() - self.cpu0 - self.graph_cpu)
        return {"localise": wall, "association": 1e3 * self.graph_wall, "localise_cpu": cpu}


class MapPipeline:
    """One map's estimator with its front end (camera maps), localiser and robots."""

    def __init__(
        self,
        slam: BearingSlam,
        *,
        localiser: PlaceLocaliser | None,
        images: ImageFrontEnd | None = None,
        robots: dict[str, RobotState] | None = None,
        pose_covariance: bool = True,
    ) -> None:
        """`images`: the front end of a camera map (it shares `robots`). `localiser`
        None: every frame goes to the estimator (an offline replay); then
        `pose_covariance` False skips the pose marginal of a JSON frame."""
        self.slam = slam
        self.localiser = localiser
        self.robots: dict[str, RobotState] = {} if robots is None else robots
        self.images = images
        if images is not None:
            images.robots = self.robots
        self.pose_covariance = pose_covariance

    # ------------------------------------------------------------ the frame
    def step(
        self,
        frame: FrameInput,
        *,
        image: ImageFeatures | None = None,
        landmark_covariances: bool = True,
    ) -> FrameStep:
        """One frame of one robot (validated by the caller against `last_accepted`):
        `image` the features of an image frame (its own observations are ignored).
        `landmark_covariances` False: a place learnt at a JSON frame takes a default
        landmark covariance instead of the graph's joint marginal."""
        clock = _Clock(image=image is not None)
        robot = self.robots.setdefault(frame.robot, RobotState())
        odometry = self._odometry(frame, robot)
        graph = self._to_graph(frame, image, clock) if self._feeds_graph(frame) else None
        if self.localiser is None:  # an offline replay: the estimator alone
            assert graph is not None
            robot.last = (frame.seq, frame.stamp)
            return self._result(frame, graph, clock, recorded=frame.observations)
        seen = self._filter_input(frame, image, robot, graph)
        result = self.localiser.step(
            self.slam,
            frame.robot,
            odometry=odometry,
            dt_s=0.0 if robot.last is None else frame.stamp - robot.last[1],
            stamp=frame.stamp,
            weighed=seen.weighed,
            quality=seen.quality,
            graph_pose=None if graph is None else _map_pose(graph.outcome),
            landmarks=seen.landmarks,
            covariances=image is None and landmark_covariances,
            hints=seen.hints,
            verify=seen.verify,
        )
        robot.last = (frame.seq, frame.stamp)
        if result.anchor:
            est = result.estimate
            anchor = (Pose2D(*(float(v) for v in est.pose_xytheta)), est.covariance)
            graph = self._to_graph(frame, image, clock, anchor=anchor)
            robot.landmark_matches = None  # a new average from the anchor on
            robot.off_graph.anchor(seq=frame.seq, odometry=odometry)
        pose, cov = self._keep(frame, robot, graph, result.estimate, odometry)
        robot.reported = self._report(frame, image, graph, result, seen)
        recorded = seen.weighed if graph is None else self._recorded(frame, graph)
        return self._result(frame, graph, clock, recorded, result, robot, pose, cov)

    def upkeep(self) -> None:
        """The estimator's work the last frame left for after its result (see
        SlamConfig.upkeep); `step` runs it first when nobody did."""
        self.slam.upkeep()

    def _feeds_graph(self, frame: FrameInput) -> bool:
        """Whether the estimator takes the frame (before the localiser's step)."""
        if self.localiser is None:
            return True
        known = frame.robot in self.slam.robots or frame.initial_pose is not None
        return known and self.localiser.feeds_graph(frame.robot)

    @staticmethod
    def _odometry(frame: FrameInput, robot: RobotState) -> Pose | None:
        """The frame's odometry, None on the robot's first frame."""
        odo = frame.odometry
        return None if odo is None or robot.last is None else (odo.dx, odo.dy, odo.dtheta)

    def _to_graph(
        self,
        frame: FrameInput,
        image: ImageFeatures | None,
        clock: _Clock,
        *,
        anchor: tuple[Pose2D, FloatArray] | None = None,
    ) -> _GraphStep:
        """The estimator takes the frame (an image frame through the front end first)."""
        with clock.graph():
            if image is not None:
                if self.images is None:
                    raise ValueError("an image frame needs a front end (a camera config)")
                done = self.images.submit(
                    frame, image.features, signature=image.signature, anchor=anchor
                )
                return _GraphStep(done.outcome, done.association)
            covariance = self.pose_covariance or self.localiser is not None
            outcome = self.slam.process(
                frame, with_covariance=covariance or self.images is not None, anchor=anchor
            )
            if self.images is not None:
                # The robot's next image frame is predicted from this pose.
                assert outcome.covariance is not None
                self.images.note_pose(frame.robot, outcome.pose, outcome.covariance)
            return _GraphStep(outcome, None)

    def _filter_input(
        self,
        frame: FrameInput,
        image: ImageFeatures | None,
        robot: RobotState,
        graph: _GraphStep | None,
    ) -> _FilterInput:
        """What the filter weighs of the frame (see the module docstring)."""
        # With the frame's new ones; a camera map's archived landmarks too.
        slam = self.slam
        landmarks = landmark_map(slam) if self.images is None else localisation_landmarks(slam)
        if image is None:
            return _FilterInput(frame.observations, landmarks=landmarks)
        assert self.images is not None and self.localiser is not None
        associator = self.images.front_end.associator
        appearance = self.localiser.appearance
        found = None if image.signature is None else appearance.match(image.signature)
        matched: list[BearingObservation] = []
        if graph is not None:
            assert graph.association is not None
            assoc = graph.association
            kinds = zip(assoc.observations, assoc.kind, strict=True)
            matched = [o for o, k in kinds if k == "landmark"]
        if graph is None or _starved(robot, len(matched), len(slam.landmarks)):
            weighed, quality = associator.match_without_pose(
                image.features, sorted(landmarks), limit=MAX_FILTER_OBSERVATIONS
            )
        else:
            pick = _spread(len(matched), MAX_FILTER_OBSERVATIONS)
            weighed = tuple(matched[i] for i in pick.tolist())
            quality = np.ones(len(weighed))

        def verify(est: FilterEstimate) -> bool:
            association = associator.associate(
                image.features,
                robot=frame.robot,
                predicted_pose=est.pose_xytheta,
                pose_cov=est.covariance,
                landmarks={label: (xy, None) for label, xy in landmarks.items()},
            )
            n = len(association.landmark_matches)
            return n >= max(VERIFY_MIN_MATCHES, VERIFY_SHARE * len(weighed))

        hints = appearance.hints(found, top=TOP_HINTS)
        return _FilterInput(weighed, quality.tolist(), hints, verify, landmarks, found)

    @staticmethod
    def _keep(
        frame: FrameInput,
        robot: RobotState,
        graph: _GraphStep | None,
        est: FilterEstimate,
        odometry: Pose | None,
    ) -> tuple[Pose2D, FloatArray]:
        """The frame's pose and (3, 3) robot-frame covariance: the graph's, or (a frame
        the graph did not take, kept off the graph) the best pose then available with
        the filter's covariance."""
        if graph is not None:
            # In the graph (also the frame that found the robot lost): its graph pose is
            # the one in the trajectory, so it is the one reported.
            outcome = graph.outcome
            assert outcome.covariance is not None
            p = outcome.pose
            robot.off_graph.on_graph((p.x, p.y, p.theta))
            return p, np.asarray(outcome.covariance)
        x, y, theta = (float(v) for v in est.pose_xytheta)
        kept = robot.off_graph.off_graph(
            seq=frame.seq,
            stamp=frame.stamp,
            odometry=odometry,
            filter_pose=(x, y, theta),
            converged=est.converged,
        )
        pose = Pose2D(*kept.pose)
        return pose, to_robot_frame(est.covariance, pose.theta)

    def _report(
        self,
        frame: FrameInput,
        image: ImageFeatures | None,
        graph: _GraphStep | None,
        result: StepResult,
        seen: _FilterInput,
    ) -> tuple[int | None, float | None]:
        """(place, confidence) the frame result reports: the localiser's place for a JSON
        frame; for an image frame the appearance place (one is learnt at a graph pose far
        from every other)."""
        if image is None:
            return result.place, result.confidence
        assert self.localiser is not None
        appearance = self.localiser.appearance
        if graph is None:
            place, confidence = appearance.best(seen.found)
            if confidence is not None:
                confidence = min(confidence, float(result.estimate.converged))
            return place, confidence
        if image.signature is None:
            return appearance.best(seen.found)
        p = graph.outcome.pose
        place, confidence, _ = appearance.observe(
            image.signature,
            robot=frame.robot,
            pose=(p.x, p.y, p.theta),
            frame=graph.outcome.frame_index,
            stamp=frame.stamp,
            found=seen.found,
        )
        return place, confidence

    @staticmethod
    def _recorded(frame: FrameInput, graph: _GraphStep) -> tuple[BearingObservation, ...]:
        assoc = graph.association
        return frame.observations if assoc is None else tuple(assoc.observations)

    def _result(
        self,
        frame: FrameInput,
        graph: _GraphStep | None,
        clock: _Clock,
        recorded: Sequence[BearingObservation],
        result: StepResult | None = None,
        robot: RobotState | None = None,
        pose: Pose2D | None = None,
        cov: FloatArray | None = None,
    ) -> FrameStep:
        outcome = None if graph is None else graph.outcome
        if pose is None:
            assert outcome is not None
            pose = outcome.pose
            cov = None if outcome.covariance is None else np.asarray(outcome.covariance)
        place, confidence = (None, None) if robot is None else robot.reported
        return FrameStep(
            robot=frame.robot,
            seq=frame.seq,
            stamp=frame.stamp,
            outcome=outcome,
            status="tracking" if result is None else result.status,
            place=place,
            confidence=confidence,
            pose=pose,
            covariance=cov,
            learnt=None if result is None else result.learnt,
            observations=tuple(recorded),
            timing_ms=clock.timing_ms(image=clock.image),
        )

    # ------------------------------------------------------------ robots
    def last_accepted(self) -> dict[str, tuple[int, float]]:
        """(seq, stamp) of each robot's last accepted frame, graph or filter only."""
        out = last_accepted(self.slam)
        out.update((name, r.last) for name, r in self.robots.items() if r.last is not None)
        return out

    def off_graph_count(self) -> int:
        """Frames kept off the graph, all robots."""
        return sum(r.off_graph.count() for r in self.robots.values())

    def off_graph_robots(self) -> list[str]:
        """Robots with frames kept off the graph, by name."""
        return sorted(name for name, r in self.robots.items() if r.off_graph.count())

    def with_off_graph(
        self, rows: dict[str, list[dict[str, Any]]], robot: str | None = None
    ) -> dict[str, list[dict[str, Any]]]:
        """The graph's trajectory rows per robot (`rows`, changed in place and returned)
        with every off-graph frame added, ordered by seq; `robot`: that robot only."""
        for name in self.off_graph_robots():
            if robot is not None and name != robot:
                continue
            graph = rows.get(name, [])
            by_seq = {int(r["seq"]): (r["x"], r["y"], r["theta"]) for r in graph}
            extra = self.robots[name].off_graph.rows(by_seq)
            if extra:
                rows[name] = sorted([*graph, *extra], key=lambda r: int(r["seq"]))
        return rows


def _map_pose(outcome: FrameOutcome) -> tuple[FloatArray, FloatArray]:
    """(pose (3,), (3, 3) map-frame covariance) of a graph frame."""
    assert outcome.covariance is not None
    p = outcome.pose
    return np.array([p.x, p.y, p.theta]), to_map_frame(outcome.covariance, p.theta)


def _spread(n: int, limit: int) -> NDArray[np.int64]:
    """Up to `limit` indices spread evenly over range(n)."""
    if n <= limit:
        return np.arange(n, dtype=np.int64)
    return np.unique(np.linspace(0, n - 1, limit).round().astype(np.int64))


def _starved(robot: RobotState, matches: int, live: int) -> bool:
    """Whether a tracked frame with `matches` pose-gated landmark matches, in a map of
    `live` live landmarks, is starved (see STARVED_SHARE); the robot's running average
    takes the frame in unless it is starved: a robot carried elsewhere stays starved until
    the filter has found it (a capped camera map, ~17 matches a frame: the average decayed
    below STARVED_MIN_AVERAGE two frames after the jump, and the kidnap went unnoticed)."""
    average = robot.landmark_matches
    starved = (
        average is not None and average >= starved_floor(live) and matches < STARVED_SHARE * average
    )
    if not starved:
        n = float(matches)
        robot.landmark_matches = n if average is None else average + AVERAGE_RATE * (n - average)
    return starved


def starved_floor(live: int) -> float:
    """The running average of matches below which no frame is starved, in a map of `live`
    live landmarks (STARVED_MIN_AVERAGE, STARVED_LIVE_SHARE, STARVED_FLOOR)."""
    return max(STARVED_FLOOR, min(STARVED_MIN_AVERAGE, STARVED_LIVE_SHARE * live))
