"""Image frames through the place localiser: camera robots initialise, get
lost and relocalise as robots with labelled bearings do (service.localisation).

`process_image(loc, slam, pipeline, frame, features, signature)` is one image frame:

- a robot the graph tracks (it came with ``initial_pose``, or was relocalised): the
  image pipeline associates the features (gated by the predicted pose) and the graph
  takes the frame; then the robot's particle filter is stepped on the frame's
  landmark matches and compared with the graph's pose (`Localiser.step`), so that a
  sustained disagreement makes the robot ``lost``. When the pose-gated association
  suddenly finds far fewer landmarks than the robot usually does (a *starved* frame:
  what a robot carried elsewhere sees, its prediction being wrong), the filter gets the
  features matched to the landmarks by descriptor alone instead, which do not depend on
  the believed pose;
- a robot the graph does not track (its first frame came without ``initial_pose``,
  or it is lost): the features are matched to every live landmark without a pose
  prior (frontend.global_match); the filter weighs these bearings, and its injection
  proposals come from the appearance places that recognition ranks highest (each a
  place's position with its heading turned by the recognised yaw offset). Once the
  filter has been converged for a few frames, its estimate is checked: the pose-gated
  association run from it must match enough landmarks (look-alike posters of an
  unmapped room can draw the filter to a pose their pose-free matches fit by chance);
  if not, the filter searches afresh. Then the frame anchors the robot's chain at the
  filter's estimate (``relocalised``): the pipeline associates it from there, and the
  graph takes it with the filter's covariance as the prior. Frames before that are
  kept off the graph (service.offgraph) as labelled frames are.

The observations returned are what the frame is recorded with (a map export carries
them): the association's for a frame the graph took, the pose-free matches the filter
weighed otherwise.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from frontend.features import Features
from graph.localiser import RELOCALISED, TRACKING
from graph.particles import FilterEstimate
from graph.slam import BearingSlam
from graph.types import BearingObservation, FrameInput, Pose2D
from service.localisation import Localised, MapLocalisation, to_map_frame
from service.vision import ImageFrameResult, ImagePipeline

__all__ = ["CameraFrame", "process_image"]

FloatArray = NDArray[np.float64]

MAX_FILTER_OBSERVATIONS = 64
"""Most bearings one frame gives the filter (spread over the panorama): a frame matches
100+ landmarks, and the filter's cost grows with them while 64 already pin the pose."""
STARVED_SHARE = 0.3
"""A frame is starved when its pose-gated landmark matches fall below this share of
the robot's running average..."""
STARVED_MIN_AVERAGE = 15.0
"""... provided that average is at least this (a robot that usually sees few landmarks
says nothing by seeing few)."""
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


def verified_matches(
    pipeline: ImagePipeline,
    features: Features,
    robot: str,
    pose_xytheta: FloatArray,
    covariance: FloatArray,
    landmarks: dict[str, FloatArray],
) -> int:
    """Landmarks the pipeline's association matches from `pose_xytheta` (nothing is
    committed: the front end is unchanged)."""
    association = pipeline.front_end.associator.associate(
        features,
        robot=robot,
        predicted_pose=pose_xytheta,
        pose_cov=covariance,
        landmarks={label: (xy, None) for label, xy in landmarks.items()},
    )
    return len(association.landmark_matches)


@dataclass(frozen=True)
class CameraFrame:
    localised: Localised
    observations: tuple[BearingObservation, ...]
    """What the frame is recorded with (see the module docstring)."""
    pipeline: ImageFrameResult | None
    """The pipeline's result when the graph took the frame."""
    timing_ms: dict[str, float]
    """association (the pipeline's association and estimator, or the pose-free
    matching), localise / localise_cpu (wall / this thread's CPU ms of everything the
    place localiser adds to the frame: all but the image pipeline), filter (the
    filter's step, wall)."""


def _spread(n: int, limit: int) -> NDArray[np.int64]:
    """Up to `limit` indices spread evenly over range(n)."""
    if n <= limit:
        return np.arange(n, dtype=np.int64)
    return np.unique(np.linspace(0, n - 1, limit).round().astype(np.int64))


def _starved(loc: MapLocalisation, robot: str, matches: int) -> bool:
    """Whether a tracked frame with `matches` pose-gated landmark matches is starved
    (see STARVED_SHARE); the robot's running average takes the frame in."""
    average = loc.landmark_matches.get(robot)
    starved = (
        average is not None and average >= STARVED_MIN_AVERAGE and matches < STARVED_SHARE * average
    )
    n = float(matches)
    loc.landmark_matches[robot] = n if average is None else average + AVERAGE_RATE * (n - average)
    return starved


def process_image(
    loc: MapLocalisation,
    slam: BearingSlam,
    pipeline: ImagePipeline,
    frame: FrameInput,
    features: Features,
    signature: NDArray[np.float32] | None,
) -> CameraFrame:
    """One image frame of one robot (validated by the caller); see the module docstring."""
    wall0, cpu0 = time.perf_counter(), time.thread_time()
    pipeline_wall = pipeline_cpu = 0.0
    robot = frame.robot
    track = loc.localiser.robots.get(robot)
    on_graph = (track is None or track.status in (TRACKING, RELOCALISED)) and (
        robot in pipeline.robots or frame.initial_pose is not None
    )
    found = None if signature is None else loc.appearance.match(signature)
    hints = loc.appearance.hints(found, top=TOP_HINTS)
    prev = loc.last.get(robot)
    odo = frame.odometry
    odometry = None if odo is None or prev is None else (odo.dx, odo.dy, odo.dtheta)

    result: ImageFrameResult | None = None
    graph_pose = None
    t0 = time.perf_counter()
    if on_graph:
        w, c = time.perf_counter(), time.thread_time()
        result = pipeline.submit(frame, features, signature=signature)
        pipeline_wall += time.perf_counter() - w
        pipeline_cpu += time.thread_time() - c
        assoc = result.association
        outcome = result.outcome
        assert outcome.covariance is not None
        p = outcome.pose
        graph_pose = (np.array([p.x, p.y, p.theta]), to_map_frame(outcome.covariance, p.theta))
        landmarks = MapLocalisation.landmark_map(slam)  # with the frame's new ones
        matched = [
            o for o, k in zip(assoc.observations, assoc.kind, strict=True) if k == "landmark"
        ]
        if _starved(loc, robot, len(matched)):
            weighed, quality = pipeline.front_end.associator.match_without_pose(
                features, sorted(landmarks), limit=MAX_FILTER_OBSERVATIONS
            )
        else:
            pick = _spread(len(matched), MAX_FILTER_OBSERVATIONS)
            weighed = tuple(matched[i] for i in pick.tolist())
            quality = np.ones(len(weighed))
        recorded = assoc.observations
        assoc_ms = result.timing_ms["association"] + result.timing_ms["estimator"]
    else:
        landmarks = MapLocalisation.landmark_map(slam)
        weighed, quality = pipeline.front_end.associator.match_without_pose(
            features, sorted(landmarks), limit=MAX_FILTER_OBSERVATIONS
        )
        recorded = weighed
        assoc_ms = 1e3 * (time.perf_counter() - t0)

    def verify(est: FilterEstimate) -> bool:
        n = verified_matches(pipeline, features, robot, est.pose_xytheta, est.covariance, landmarks)
        return n >= max(VERIFY_MIN_MATCHES, VERIFY_SHARE * len(weighed))

    t1 = time.perf_counter()
    step = loc.localiser.step(
        robot,
        odometry=odometry,
        dt_s=0.0 if prev is None else frame.stamp - prev[1],
        labels=[o.label for o in weighed],
        bearings_rad=[o.bearing_rad for o in weighed],
        sigmas_rad=[o.sigma_rad for o in weighed],
        quality=quality.tolist(),
        landmarks=landmarks,
        graph_pose=graph_pose,
        rng=loc.rng,
        frame=slam.frame_count,
        stamp=frame.stamp,
        ids={rec.label: lid for lid, rec in slam.landmarks.items()},
        hints=hints,
        verify=verify,
    )
    step_ms = 1e3 * (time.perf_counter() - t1)
    est = step.estimate
    loc.last[robot] = (frame.seq, frame.stamp)
    if step.anchor:
        anchor = (Pose2D(*(float(v) for v in est.pose_xytheta)), est.covariance)
        w, c = time.perf_counter(), time.thread_time()
        result = pipeline.submit(frame, features, signature=signature, anchor=anchor)
        pipeline_wall += time.perf_counter() - w
        pipeline_cpu += time.thread_time() - c
        recorded = result.association.observations
        loc.landmark_matches.pop(robot, None)  # a new average from the anchor on
    if result is not None:
        outcome = result.outcome
        assert outcome.covariance is not None
        p = outcome.pose
        pose, cov = p, np.asarray(outcome.covariance)
        if step.anchor:
            loc.off_graph.anchor(robot, seq=frame.seq, odometry=odometry)
        loc.off_graph.on_graph(robot, (p.x, p.y, p.theta))
        if signature is not None:
            place, confidence, _ = loc.appearance.observe(
                signature,
                robot=robot,
                pose=(p.x, p.y, p.theta),
                frame=outcome.frame_index,
                stamp=frame.stamp,
                found=found,
            )
        else:
            place, confidence = loc.appearance.best(found)
    else:
        pose, cov = loc.keep_off_graph(frame, odometry, est)
        place, confidence = loc.appearance.best(found)
        if confidence is not None:
            confidence = min(confidence, float(est.converged))
    loc.reported[robot] = (place, confidence)
    # What the place localiser adds to the frame: everything but the image pipeline.
    ms = 1e3 * (time.perf_counter() - wall0 - pipeline_wall)
    cpu_ms = 1e3 * (time.thread_time() - cpu0 - pipeline_cpu)
    localised = Localised(
        robot,
        frame.seq,
        frame.stamp,
        None if result is None else result.outcome,
        step.status,
        place,
        confidence,
        pose,
        cov,
        step.learnt,
        ms,
    )
    timing = {"association": assoc_ms, "localise": ms, "localise_cpu": cpu_ms, "filter": step_ms}
    return CameraFrame(localised, tuple(recorded), result, timing)
