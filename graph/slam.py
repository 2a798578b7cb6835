"""One map's estimator: frames in, a bounded bearing-only factor graph inside.

`BearingSlam.process(frame)` runs steps 3-5 of DESIGN.md's frame pipeline for
labelled observations: association by label, delayed landmark initialisation,
one iSAM2 update (which also marginalises the pose leaving each robot's window),
then the landmark budget: while more landmarks are live than the cap, the
policy picks one and it is marginalised out (Schur complement, see graph.isam) and
archived; seen again, it comes back under its id (graph.archive).
With `graph_frame_distance_m` set, only some frames enter the graph; the others are
tracked against it (`_track`, graph.tracking) and follow it.
"""

from __future__ import annotations

import logging
import math
import time
from array import array
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from graph.angles import wrap_angles
from graph.archive import ArchivedLandmark, LandmarkArchive
from graph.config import SlamConfig
from graph.factors import (
    anchor_prior_factor,
    bearing_factor,
    from_pose2,
    is_landmark_key,
    landmark_key,
    landmark_prior_factor,
    odometry_factor,
    odometry_sigmas,
    pose_key,
    pose_prior_factor,
    to_pose2,
    vague_link,
)
from graph.heap import release_free_heap
from graph.isam import IncrementalGraph
from graph.landmarks import CandidateTrack, LandmarkRecord, Ray
from graph.policies import LandmarkTable, Removal, get_policy, information_content
from graph.tracking import Motion, compose_motion, solve_pose, tracked_covariance
from graph.trajectory import PoseRow, Trajectory, pose_rows
from graph.triangulation import Triangulation, parallax, triangulate
from graph.types import BearingObservation, FrameInput, Pose2D
from graph.validation import validate_frame

_SHRINK_SLACK = 20
"""A window shrinks by an extra pose beyond window_factor_bound (or window_marginals)
* (1 + 1/this)."""
_SWEEP_EVERY = 50
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0

log = logging.getLogger(__name__)


@dataclass(slots=True)
class _Robot:
    slot: int
    last_seq: int
    last_stamp: float
    next_index: int
    window: deque[tuple[int, int]] = field(default_factory=deque)
    """(pose key, frame index) of the robot's newest poses, oldest first."""
    keyframes: deque[tuple[int, int]] = field(default_factory=deque)
    """(pose key, frame index) of older poses kept in the graph as keyframes."""
    motion: Motion | None = None
    """Odometry since the robot's newest graph frame (window[-1]), when frames were
    tracked since (see SlamConfig.graph_frame_distance_m)."""
    tracked: tuple[int, NDArray[np.float64]] | None = None
    """The newest frame's index (its trajectory entry is its pose relative to window[-1])
    and its bearings' (3, 3) information, when that frame was tracked; None when it is
    in the graph."""


@dataclass(frozen=True, slots=True)
class RemovalRecord:
    """One entry of the removal log: which landmark left the graph, when and why."""

    frame: int
    stamp: float
    landmark_id: int
    label: str
    position: tuple[float, float]
    observed_from: tuple[float, float]
    count: int
    removal: Removal

    def as_dict(self) -> dict[str, Any]:
        return {
            "frame": self.frame,
            "stamp": self.stamp,
            "landmark_id": self.landmark_id,
            "label": self.label,
            "x": self.position[0],
            "y": self.position[1],
            "observed_from": {
                "x": self.observed_from[0],
                "y": self.observed_from[1],
                "n": self.count,
            },
            "policy": self.removal.policy,
            "reason": self.removal.reason,
            "details": self.removal.details,
        }


@dataclass(frozen=True, slots=True)
class FrameOutcome:
    """What one frame did to the map."""

    frame_index: int
    robot: str
    seq: int
    stamp: float
    pose: Pose2D
    covariance: NDArray[np.float64] | None
    """(3, 3) covariance of (x, y, theta) in the robot frame, or None if not asked for."""
    observed: tuple[int, ...]
    added: tuple[int, ...]
    marginalised: tuple[int, ...]
    """Landmarks the budget removed since the frame before: in this frame, or in the
    upkeep after the frame before (see SlamConfig.upkeep)."""
    live: int
    timing_ms: dict[str, float]
    restored: tuple[int, ...] = ()
    """Archived landmarks that came back into the graph this frame (graph.archive)."""


@dataclass(frozen=True, slots=True)
class _Plan:
    """Everything a frame will change, prepared before anything changes."""

    key: int
    predicted: gtsam.Pose2
    factors: list[gtsam.NonlinearFactor]
    values: gtsam.Values
    observed: list[tuple[int, float]]
    factored: tuple[int, ...]
    """Landmarks of `observed` that got a bearing factor (see max_landmark_factors)."""
    candidates: dict[str, CandidateTrack]
    new_landmarks: list[tuple[str, Triangulation, tuple[Ray, ...]]]
    exiting: tuple[int, int] | None
    """The (key, frame) leaving the robot's window this frame, if any."""
    promoted: bool
    """Whether `exiting` stays in the graph as a keyframe."""
    leaving: tuple[tuple[int, int], ...]
    """Poses (key, frame) marginalised this frame: `exiting` or the oldest keyframe."""
    restored: tuple[tuple[int, tuple[Ray, ...]], ...] = ()
    """Archived landmarks (id, the rays that got a factor) coming back this frame."""
    exit_due: bool = False
    """The robot's oldest window pose leaves in the upkeep after this frame (see
    SlamConfig.window_exit_after_frame), not in the frame's update."""


class BearingSlam:
    """A bearing-only map with a landmark budget and a pose window per robot."""

    def __init__(
        self,
        config: SlamConfig | None = None,
        *,
        rng: np.random.Generator,
        removal_sink: Callable[[RemovalRecord], None] | None = None,
        removal_memory: int = 1000,
        release_heap: bool = True,
        trajectory_sink: Callable[[list[PoseRow]], None] | None = None,
    ) -> None:
        """`removal_sink` receives every removal record (e.g. to append it to durable
        storage); only the last `removal_memory` records stay in `self.removals`, so a
        lifelong map's memory does not grow with its removal log.

        `release_heap`: after every frame that updated the graph, hand the heap's free
        pages back to the OS (graph.heap, ~0.2 ms): the dense blocks an update builds and
        frees (marginals, a landmark removal's Schur complement) would otherwise stay
        resident, scattered through the heap, and the process's steady RSS would step up
        over a lifelong run. The estimate does not change.

        `trajectory_sink` receives the trajectory rows that became final in a frame (their
        poses were marginalised and will not change again, graph.trajectory), and they are
        then forgotten here, so that memory does not grow with the frames: `trajectory()`
        returns only the rows still held. Without a sink every row stays here."""
        self.config = config or SlamConfig()
        self._policy = get_policy(self.config.policy)
        self._rng = rng
        self._graph = IncrementalGraph(self.config)
        self._robots: dict[str, _Robot] = {}
        self._landmarks: dict[int, LandmarkRecord] = {}
        self._label_to_id: dict[str, int] = {}
        self._candidates: dict[str, CandidateTrack] = {}
        self._archive = LandmarkArchive()
        self.restoration_count = 0
        """Archived landmarks that came back into the graph, in all."""
        self._next_landmark_id = 0
        self._frames = 0
        self.gated_observations = 0
        """Observations of live landmarks refused by the innovation gate, in all."""
        self.removals: deque[RemovalRecord] = deque(maxlen=removal_memory)
        self.removal_count = 0
        self._removal_sink = removal_sink
        self._release_heap = release_heap
        self._trajectory_sink = trajectory_sink
        # Per-frame trajectory: final estimates of marginalised poses, live keys looked up.
        self._trajectory = Trajectory()
        self._live_frames: dict[int, int] = {}
        self._last_factor: dict[int, int] = {}
        """Frame index of each live landmark's newest bearing factor (max_landmark_factors)."""
        # Marginalised non-keyframe frames, by the live keyframe their pose is relative to.
        self._anchored: dict[int, array[int]] = {}
        self._window_factors: dict[int, int] = {}
        """Bearing factors on each pose while it is in its robot's window (kept only
        with SlamConfig.window_factor_bound)."""
        self._pending: FrameInput | None = None
        """The frame whose upkeep has not run yet (see SlamConfig.upkeep)."""
        self._exit_due = False
        """The pending upkeep starts with the window exit its frame left (see
        SlamConfig.window_exit_after_frame)."""
        self._upkeeps = 0
        self._unreported: list[RemovalRecord] = []
        self._final_rows: list[list[PoseRow]] = []
        """Removal records and final trajectory rows not handed to the sinks yet: they go
        out with the next frame's outcome, whose `marginalised` names those removals."""

    # ---------------------------------------------------------------- queries
    @property
    def frame_count(self) -> int:
        return self._frames

    @property
    def graph_frame_count(self) -> int:
        """Frames that entered the graph (the others were tracked)."""
        return sum(r.next_index for r in self._robots.values())

    @property
    def graph(self) -> IncrementalGraph:
        return self._graph

    @property
    def landmarks(self) -> dict[int, LandmarkRecord]:
        """Live landmarks by id (read-only view; do not mutate)."""
        return self._landmarks

    @property
    def archive(self) -> LandmarkArchive:
        """Removed landmarks that are not live (read-only view; see graph.archive)."""
        return self._archive

    @property
    def robots(self) -> list[str]:
        return list(self._robots)

    @property
    def candidate_count(self) -> int:
        return len(self._candidates)

    def landmark_position(self, landmark_id: int) -> NDArray[np.float64]:
        return self._graph.point(landmark_key(landmark_id))

    def landmark_positions(self, ids: list[int]) -> NDArray[np.float64]:
        """(N, 2) positions of live landmarks, metres (one pass over the estimate)."""
        return self._graph.points([landmark_key(i) for i in ids])

    def landmark_covariances(self, ids: list[int]) -> NDArray[np.float64]:
        """(N, 2, 2) marginal covariances of live landmarks, m^2."""
        return self._graph.landmark_covariances([landmark_key(i) for i in ids])

    def landmark_joint_covariance(self, ids: list[int]) -> NDArray[np.float64]:
        """(2N, 2N) joint marginal covariance of live landmarks, m^2, in the order of
        `ids` (x, y of each)."""
        return self._graph.landmark_joint_covariance([landmark_key(i) for i in ids])

    def trajectory(self, robot: str | None = None) -> dict[str, NDArray[np.float64]]:
        """Per robot, an (N, 5) array of frames: seq, stamp, x, y, theta.

        Poses still in the graph carry the current estimate; marginalised poses
        keep the last estimate they had. With a trajectory sink, the rows already
        handed to it are not here (see `__init__`).
        """
        rows = self._trajectory.rows()
        poses = rows.pose
        # All live poses, then all anchored frames, each in one array operation (a
        # map's trajectory is published every few frames): the same values, element by
        # element, as one pose and one keyframe at a time.
        live = self._live_frames
        if live:
            idx = rows.index(np.fromiter(live.keys(), np.int64, len(live)))
            poses[idx] = self._graph.poses_xytheta(np.fromiter(live.values(), np.uint64, len(live)))
        if self._anchored:
            anchored = self._anchored
            base = self._graph.poses_xytheta(np.fromiter(anchored, np.uint64, len(anchored)))
            counts = [len(frames) for frames in anchored.values()]
            idx = rows.index(np.frombuffer(b"".join(anchored.values()), dtype=np.int64))
            rel = poses[idx]
            each = np.repeat(base, counts, axis=0)  # each anchored frame's keyframe
            # math's cos and sin, as one keyframe at a time took them (numpy's may differ
            # in the last bit).
            c = np.repeat([math.cos(t) for t in base[:, 2].tolist()], counts)
            s = np.repeat([math.sin(t) for t in base[:, 2].tolist()], counts)
            poses[idx, 0] = each[:, 0] + c * rel[:, 0] - s * rel[:, 1]
            poses[idx, 1] = each[:, 1] + s * rel[:, 0] + c * rel[:, 1]
            poses[idx, 2] = wrap_angles(each[:, 2] + rel[:, 2])
        seq = rows.seq.astype(np.float64)
        out: dict[str, NDArray[np.float64]] = {}
        for name, state in self._robots.items():
            if robot is not None and name != robot:
                continue
            mask = rows.slot == state.slot
            out[name] = np.column_stack([seq[mask], rows.stamp[mask], poses[mask]])
        return out

    @property
    def keyframe_count(self) -> int:
        """Poses kept in the graph as keyframes, every robot's (see keyframe_placement)."""
        return sum(len(r.keyframes) for r in self._robots.values())

    @property
    def held_trajectory_rows(self) -> int:
        """Trajectory rows whose pose can still change (bounded by the graph's size)."""
        return self._trajectory.held_count

    # ---------------------------------------------------------------- the pipeline
    def process(
        self,
        frame: FrameInput,
        *,
        with_covariance: bool = True,
        anchor: tuple[Pose2D, NDArray[np.float64]] | None = None,
    ) -> FrameOutcome:
        """Add one frame. Raises InvalidFrame (map unchanged) or EstimationError.

        `anchor` = (pose, (3, 3) map-frame covariance of x, y, theta) from the place
        localiser: the frame's pose gets a prior there instead of the initial pose (a
        new robot) or of the odometry (a robot that was lost: its chain is re-anchored;
        the odometry across the gap is kept only as a vague link).
        """
        robot = self._robots.get(frame.robot)
        validate_frame(
            frame,
            last_seq=robot.last_seq if robot else None,
            last_stamp=robot.last_stamp if robot else None,
            require_initial_pose=anchor is None,
        )
        self.upkeep()  # after the checks: a refused frame leaves a pending upkeep pending
        t0 = time.perf_counter()
        motion = None
        if robot is not None and anchor is None and self.config.graph_frame_distance_m is not None:
            motion = self._motion(robot, frame)
            if not self._is_graph_frame(frame, motion):
                return self._track(frame, robot, motion, with_covariance, t0)
            if motion.frames == 1:
                motion = None  # one step: the frame's own odometry factor, as without
        plan = self._plan(frame, robot, anchor, motion)
        t1 = time.perf_counter()
        # Estimates before the update: what a marginalised pose keeps.
        before = self._poses_before_exit(robot, plan.exiting, plan.promoted, plan.leaving)
        self._graph.update(
            plan.factors,
            plan.values,
            marginalise=[k for k, _ in plan.leaving],
            drop=self._dropped_observations(plan.exiting, plan.promoted),
        )
        t2 = time.perf_counter()
        robot = self._commit(frame, robot, plan, before)
        pose = from_pose2(self._graph.pose(plan.key))
        if self.config.upkeep != "in_frame":
            self._note_exit(plan)
            self._pending = frame
            self._exit_due = plan.exit_due
        else:
            self._enforce_budget(frame)
            self._note_exit(plan)
            self._bound_window(robot)
        t3 = time.perf_counter()
        covariance = self._graph.pose_covariance(plan.key).copy() if with_covariance else None
        t4 = time.perf_counter()
        return FrameOutcome(
            frame_index=self._frames - 1,
            robot=frame.robot,
            seq=frame.seq,
            stamp=frame.stamp,
            pose=pose,
            covariance=covariance,
            observed=tuple(lid for lid, _ in plan.observed),
            added=tuple(
                self._label_to_id[label]
                for label, _, _ in plan.new_landmarks
                if label in self._label_to_id
            ),
            marginalised=self._report(),
            live=len(self._landmarks),
            restored=tuple(lid for lid, _ in plan.restored),
            timing_ms={
                "prepare": 1e3 * (t1 - t0),
                "update": 1e3 * (t2 - t1),
                "budget": 1e3 * (t3 - t2),
                "covariance": 1e3 * (t4 - t3),
                "total": 1e3 * (t4 - t0),
            },
        )

    def upkeep(self) -> None:
        """The work the last frame left (see SlamConfig.upkeep; nothing with "in_frame"):
        the landmark budget, a second window exit and keyframe thinning, then
        iSAM2's relinearisation ("after_frame", or of the variables the frame's update
        held back: SlamConfig.relinearise_budget). The service calls it once
        the frame's result is sent; `process` calls it first when nobody did, so a
        sequence of frames gives the same map however the upkeeps were timed. Raises
        EstimationError as `process` does."""
        frame, self._pending = self._pending, None
        if frame is None:
            return
        exit_due, self._exit_due = self._exit_due, False
        relinearise = False
        if self.config.upkeep == "after_frame":
            self._upkeeps += 1
            relinearise = self._upkeeps % self.config.relinearize_skip == 0
        # The upkeep's updates relinearise as they do inside a frame: after their Schur
        # complements, taken at the linearisation point the frame's update used.
        # Relinearising first, in a step of its own, cost accuracy: on MRCLAM-6 at cap 8
        # (coverage) robot 2's ATE went from 0.205 to 0.305 m, robot 5's from 0.308 to
        # 0.519 m. The last step stands for the relinearisation at the start of the next
        # frame's update, which no longer does it.
        self._graph.relinearising = relinearise
        robot = self._robots[frame.robot]
        if self._exits_after_frame:
            # What the next frame's factors touch stays at the Bayes tree's root.
            self._graph.root_keys = (
                robot.window[-1][0],
                *(landmark_key(lid) for lid in self._in_view(frame)),
            )
        try:
            if exit_due:  # first, where the frame's own update would have made it
                self._exit_oldest(robot)
            self._enforce_budget(frame)
            self._bound_window(robot)
            if relinearise or self._graph.holding:
                # Also what the frame's update held back (relinearise_budget), now that
                # its answer is sent: after the removals, whose Schur complements are then
                # taken where a frame's are. Before them, on the dense lifelong world
                # (4 000 frames): ATE 0.231 m (0.085 aligned) against 0.181 (0.071).
                self._graph.relinearise()
        finally:
            self._graph.relinearising = False
            self._graph.root_keys = ()

    def skip_upkeep(self) -> None:
        """Drop the pending upkeep (after it failed: the next frame's upkeep takes the
        budget up again)."""
        self._pending = None
        self._exit_due = False

    @property
    def _exits_after_frame(self) -> bool:
        """Does a frame's window exit wait for its upkeep (SlamConfig.window_exit_after_frame)?"""
        return self.config.upkeep != "in_frame" and self.config.window_exit_after_frame

    @property
    def upkeep_pending(self) -> bool:
        """The last frame's upkeep has not run yet."""
        return self._pending is not None

    def settle(self) -> None:
        """Run the pending upkeep and hand its removal records and final trajectory rows
        to the sinks now (the end of an offline run), instead of with the next frame."""
        self.upkeep()
        self._report()

    def _note_exit(self, plan: _Plan) -> None:
        if plan.promoted and plan.exiting is not None:
            # A new keyframe joins the marginal factors its pose was already in.
            self._graph.marginal_keys.extend(self._graph.neighbourhoods(plan.exiting[0]))

    def _bound_window(self, robot: _Robot) -> None:
        self._shrink_window(robot)
        self._thin_keyframes()
        if self._release_heap:
            release_free_heap()

    def _report(self) -> tuple[int, ...]:
        """Hand the removal records and final trajectory rows made since the last
        outcome to the sinks; the removed landmarks' ids."""
        removals, self._unreported = self._unreported, []
        rows, self._final_rows = self._final_rows, []
        if self._removal_sink is not None:
            for entry in removals:
                self._removal_sink(entry)
        if self._trajectory_sink is not None:
            for batch in rows:
                self._trajectory_sink(batch)
        return tuple(entry.landmark_id for entry in removals)

    def _motion(self, robot: _Robot, frame: FrameInput) -> Motion:
        """The robot's odometry since its last graph frame, this frame's included."""
        assert frame.odometry is not None  # validated
        odo = frame.odometry
        sigmas = odometry_sigmas(odo, self.config, frame.stamp - robot.last_stamp)
        return compose_motion(robot.motion, (odo.dx, odo.dy, odo.dtheta), sigmas)

    def _is_graph_frame(self, frame: FrameInput, motion: Motion) -> bool:
        """Does this frame enter the graph (see SlamConfig.graph_frame_distance_m)?"""
        cfg = self.config
        assert cfg.graph_frame_distance_m is not None
        x, y, theta = motion.xyt
        if math.hypot(x, y) >= cfg.graph_frame_distance_m:
            return True
        if abs(theta) >= cfg.graph_frame_angle_rad or motion.frames >= cfg.graph_frame_max_gap:
            return True
        seen = {o.label for o in frame.observations if o.label in self._label_to_id}
        return len(seen) < cfg.graph_frame_min_landmarks

    def _track(
        self, frame: FrameInput, robot: _Robot, motion: Motion, with_covariance: bool, t0: float
    ) -> FrameOutcome:
        """A frame that stays out of the graph: its pose from its bearings to the live
        landmarks (held fixed) and the odometry since the robot's last graph frame (held
        fixed too), kept relative to that frame so that it follows the graph's later
        corrections. The landmarks' observation-position means count it; nothing else in
        the map changes, and its odometry goes into the next graph frame's factor."""
        base_key = robot.window[-1][0]
        base = self._graph.pose(base_key)
        observed, sigmas = self._live_observations(frame, base.compose(motion.pose))
        xy = self._graph.points([landmark_key(lid) for lid, _ in observed]).reshape(-1, 2)
        solved = solve_pose(
            base,
            motion,
            xy,
            np.array([z for _, z in observed], dtype=np.float64),
            np.array(sigmas, dtype=np.float64),
            self.config.huber_k,
        )
        t1 = time.perf_counter()
        covariance = (
            tracked_covariance(self._graph.pose_covariance(base_key), motion, solved.information)
            if with_covariance
            else None
        )
        t2 = time.perf_counter()
        # Commit (nothing above changed the map).
        rel = base.between(solved.pose)
        frame_index = self._frames
        robot.last_seq = frame.seq
        robot.last_stamp = frame.stamp
        robot.motion = motion
        robot.tracked = (frame_index, solved.information)
        self._trajectory.append(frame_index, robot.slot, frame.seq, frame.stamp, rel)
        self._anchored.setdefault(base_key, array("q")).append(frame_index)
        here = np.array([solved.pose.x(), solved.pose.y()])
        for lid, _ in observed:
            self._landmarks[lid].observe(here, frame.stamp)
        self._count_frame()
        return FrameOutcome(
            frame_index=frame_index,
            robot=frame.robot,
            seq=frame.seq,
            stamp=frame.stamp,
            pose=from_pose2(solved.pose),
            covariance=covariance,
            observed=tuple(lid for lid, _ in observed),
            added=(),
            marginalised=self._report(),
            live=len(self._landmarks),
            timing_ms={
                "prepare": 1e3 * (t1 - t0),
                "update": 0.0,
                "budget": 0.0,
                "covariance": 1e3 * (t2 - t1),
                "total": 1e3 * (t2 - t0),
            },
        )

    def latest_pose(self, robot: str) -> gtsam.Pose2:
        """The current estimate of the robot's newest frame (KeyError: unknown robot)."""
        state = self._robots[robot]
        base = self._graph.pose(state.window[-1][0])
        return base if state.tracked is None else base.compose(self._traj_pose_at(state.tracked[0]))

    def latest_pose_covariance(self, robot: str) -> NDArray[np.float64]:
        """(3, 3) covariance of the robot's newest frame (x, y, theta in its own frame)."""
        state = self._robots[robot]
        cov = self._graph.pose_covariance(state.window[-1][0])
        if state.tracked is None or state.motion is None:
            return cov.copy()
        return tracked_covariance(cov, state.motion, state.tracked[1])

    def _plan(
        self,
        frame: FrameInput,
        robot: _Robot | None,
        anchor: tuple[Pose2D, NDArray[np.float64]] | None = None,
        motion: Motion | None = None,
    ) -> _Plan:
        cfg = self.config
        frame_index = self._frames
        factors: list[gtsam.NonlinearFactor] = []
        values = gtsam.Values()
        if robot is None:
            slot = len(self._robots)
            key = pose_key(slot, 0)
            if anchor is not None:
                predicted = to_pose2(anchor[0])
                factors.append(anchor_prior_factor(key, anchor[0], anchor[1], cfg))
            else:
                assert frame.initial_pose is not None  # validated
                predicted = to_pose2(frame.initial_pose)
                factors.append(pose_prior_factor(key, frame.initial_pose, cfg))
            exiting: tuple[int, int] | None = None
            promoted = False
            leaving: tuple[tuple[int, int], ...] = ()
            exit_due = False
        else:
            key = pose_key(robot.slot, robot.next_index)
            assert frame.odometry is not None  # validated
            previous = robot.window[-1][0]
            if anchor is not None:
                predicted = to_pose2(anchor[0])
                factors.append(anchor_prior_factor(key, anchor[0], anchor[1], cfg))
                gap = self._graph.pose(previous).between(predicted)
                factors.append(
                    odometry_factor(
                        previous, key, vague_link(gap), cfg, frame.stamp - robot.last_stamp
                    )
                )
            elif motion is not None:  # tracked frames since the previous graph frame
                predicted = self._graph.pose(previous).compose(motion.pose)
                noise = gtsam.noiseModel.Gaussian.Covariance(motion.covariance)
                factors.append(gtsam.BetweenFactorPose2(previous, key, motion.pose, noise))
            else:
                predicted = self._graph.pose(previous).compose(
                    gtsam.Pose2(frame.odometry.dx, frame.odometry.dy, frame.odometry.dtheta)
                )
                factors.append(
                    odometry_factor(
                        previous, key, frame.odometry, cfg, frame.stamp - robot.last_stamp
                    )
                )
            full = self._window_full(robot)
            exit_due = full and self._exits_after_frame
            exiting = robot.window[0] if full and not exit_due else None
            promoted, leaving = self._window_exit(robot, exiting)
        values.insert(key, predicted)

        observed, sigmas = self._live_observations(frame, predicted)
        touched: dict[str, CandidateTrack] = {}
        if cfg.allow_new_landmarks:
            for obs in frame.observations:
                if obs.label not in self._label_to_id:
                    track = self._candidates.get(obs.label) or CandidateTrack(obs.label)
                    ray = Ray(key, frame_index, frame.stamp, obs.bearing_rad, self._sigma(obs))
                    touched[obs.label] = track.with_ray(ray, cfg.max_rays, cfg.candidate_first_rays)
        chosen = self._factor_choice(observed)
        for i in chosen:
            lid, bearing = observed[i]
            factors.append(
                bearing_factor(
                    key, landmark_key(lid), bearing, sigmas[i], cfg.huber_k, cfg.bearing_loss
                )
            )

        leaving_keys = {k for k, _ in leaving}
        new_landmarks: list[tuple[str, Triangulation, tuple[Ray, ...]]] = []
        restored: list[tuple[int, tuple[Ray, ...]]] = []
        for label, track in list(touched.items()):
            rays = tuple(
                r
                for r in track.rays
                if r.pose_key == key
                or (r.pose_key in self._graph and r.pose_key not in leaving_keys)
            )
            touched[label] = CandidateTrack(label, rays, track.last_frame)
            archived = self._archive.by_label(label) if cfg.restore_archived else None
            if archived is not None:
                if LandmarkArchive.admits(
                    archived,
                    frame_index,
                    len(rays),
                    after_frames=cfg.restore_after_frames,
                    min_rays=cfg.restore_min_rays,
                    backoff=cfg.restore_backoff,
                ):
                    tri = self._triangulate(rays, key, predicted)
                    used = self._restore(archived, rays, values, factors, tri)
                    restored.append((archived.id, used))
                continue
            first = tuple(r for r in track.rays[: cfg.candidate_first_rays] if r in rays)
            tri = self._triangulate(rays, key, predicted)
            if tri is None and first:
                # The first rays may disagree with a chain that drifted since: start from
                # the newer ones, and let the first rays' factors pull the chain.
                tri = self._triangulate(rays[len(first) :], key, predicted)
            if tri is None:
                continue
            triangulation, used = tri
            used = (*(r for r in first if r not in used), *used)
            lid = self._next_landmark_id + len(new_landmarks)
            values.insert(landmark_key(lid), triangulation.point)
            factors.extend(
                self._landmark_factors(lid, triangulation.point, used, cfg.landmark_prior_sigma_m)
            )
            new_landmarks.append((label, triangulation, used))
        return _Plan(
            key,
            predicted,
            factors,
            values,
            observed,
            tuple(observed[i][0] for i in chosen),
            touched,
            new_landmarks,
            exiting,
            promoted,
            leaving,
            restored=tuple(restored),
            exit_due=exit_due,
        )

    def _restore(
        self,
        entry: ArchivedLandmark,
        rays: tuple[Ray, ...],
        values: gtsam.Values,
        factors: list[gtsam.NonlinearFactor],
        triangulated: tuple[Triangulation, tuple[Ray, ...]] | None = None,
    ) -> tuple[Ray, ...]:
        """An archived landmark back in the graph (its initial value goes into `values`):
        a new variable under its own key (the old one was marginalised), initialised at
        the archived estimate, with a bearing factor per ray and a weak prior there. When
        the rays it came back with `triangulated` (every check of a new landmark passed),
        it starts there instead, with factors on the triangulation's rays: the map may
        have moved since the landmark was removed, and the archived estimate was made in
        the map as it was then (MRCLAM-6 robot 2 at cap 8: starting every restored
        landmark at its archived estimate took ATE from 0.26 to 0.41 m).

        No double counting: what the landmark's earlier observations said is already in
        the graph, in the marginal its removal left on the poses that saw it. A prior
        with the archived covariance would count that information a second time, so
        the archive gives at most the initial value (restored at its first observation,
        unless the hysteresis holds it back). The prior
        (restore_prior_sigma_m, 5 m: information 0.04 per m^2, against ~100 of a
        landmark located to 0.1 m) is what keeps a landmark seen by a single bearing
        well-posed (unobservable along the ray otherwise, which iSAM2 refuses as an
        indeterminant system); the double counting it adds is that small, the same weak
        prior a new landmark gets (landmark_prior_sigma_m)."""
        point = np.array(entry.position, dtype=np.float64)
        if triangulated is not None:
            point, rays = np.asarray(triangulated[0].point, dtype=np.float64), triangulated[1]
        values.insert(landmark_key(entry.id), point)
        factors.extend(
            self._landmark_factors(entry.id, point, rays, self.config.restore_prior_sigma_m)
        )
        return rays

    def _landmark_factors(
        self,
        lid: int,
        point: NDArray[np.float64],
        rays: Iterable[Ray],
        prior_sigma_m: float | None,
    ) -> list[gtsam.NonlinearFactor]:
        """A bearing factor per ray on landmark `lid`, and a weak prior at `point` (none
        when `prior_sigma_m` is None): what a landmark entering the graph gets."""
        cfg = self.config
        lkey = landmark_key(lid)
        out: list[gtsam.NonlinearFactor] = [
            bearing_factor(
                r.pose_key, lkey, r.bearing_rad, r.sigma_rad, cfg.huber_k, cfg.bearing_loss
            )
            for r in rays
        ]
        if prior_sigma_m is not None:
            out.append(landmark_prior_factor(lkey, point, prior_sigma_m))
        return out

    def _sigma(self, obs: BearingObservation) -> float:
        return obs.sigma_rad if obs.sigma_rad is not None else self.config.bearing_sigma_rad

    def _live_observations(
        self, frame: FrameInput, predicted: gtsam.Pose2
    ) -> tuple[list[tuple[int, float]], list[float]]:
        """(landmark id, bearing) and sigma of the frame's observations of live landmarks,
        without those the innovation gate refuses at the `predicted` pose."""
        observed: list[tuple[int, float]] = []
        sigmas: list[float] = []
        for obs in frame.observations:
            lid = self._label_to_id.get(obs.label)
            if lid is not None:
                observed.append((lid, obs.bearing_rad))
                sigmas.append(self._sigma(obs))
        return self._gate(observed, sigmas, predicted)

    def _gate(
        self, observed: list[tuple[int, float]], sigmas: list[float], predicted: gtsam.Pose2
    ) -> tuple[list[tuple[int, float]], list[float]]:
        """The observations of live landmarks without the outliers the innovation gate
        finds (counted in `gated_observations`; they get no factor). An outlier: a bearing
        more than max_innovation_rad from the one predicted at the odometry's pose, of a
        landmark at least gate_min_age_frames old, in a frame where another observation
        lies within gate_confirm_rad of its prediction (that one confirms the pose, so
        the odd one out is the observation, not the pose). A young landmark's large
        innovation is more often the landmark's own error, which its observations must
        be free to correct; a frame with one observation has nothing to confirm it."""
        cfg = self.config
        gate = cfg.max_innovation_rad
        if gate is None or len(observed) < 2:
            return observed, sigmas
        xy = self._graph.points([landmark_key(lid) for lid, _ in observed])
        d = xy - np.array([predicted.x(), predicted.y()])
        expected = np.arctan2(d[:, 1], d[:, 0]) - predicted.theta()
        innovation = np.abs(wrap_angles(np.array([z for _, z in observed]) - expected))
        horizon = self._frames - cfg.gate_min_age_frames
        outlier = [
            i
            for i, (lid, _) in enumerate(observed)
            if innovation[i] > gate
            and self._landmarks[lid].added_frame <= horizon
            and any(innovation[j] <= cfg.gate_confirm_rad for j in range(len(observed)) if j != i)
        ]
        if not outlier:
            return observed, sigmas
        self.gated_observations += len(outlier)
        log.debug(
            "gated %d of %d observations (innovations %s deg)",
            len(outlier),
            len(observed),
            np.round(np.degrees(innovation), 1).tolist(),
        )
        keep = [i for i in range(len(observed)) if i not in outlier]
        return [observed[i] for i in keep], [sigmas[i] for i in keep]

    def _factor_choice(self, observed: list[tuple[int, float]]) -> list[int]:
        """Indices of the observations of live landmarks that get a bearing factor: all
        of them, or (max_landmark_factors) those whose landmark's last factor is oldest,
        ties broken by a low-discrepancy sequence over the bearings (an even spread
        around the robot, no rng needed)."""
        bound = self.config.max_landmark_factors
        if bound is None or len(observed) <= bound:
            return list(range(len(observed)))
        by_bearing = sorted(range(len(observed)), key=lambda i: observed[i][1])
        spread = {i: (rank * _GOLDEN) % 1.0 for rank, i in enumerate(by_bearing)}
        order = sorted(
            range(len(observed)),
            key=lambda i: (self._last_factor.get(observed[i][0], -1), spread[i]),
        )
        return sorted(order[:bound])

    def _dropped_observations(self, exiting: tuple[int, int] | None, promoted: bool) -> list[int]:
        """Factor indices of the landmark observations of a pose leaving the window
        without becoming a keyframe, when `drop_window_observations` is set."""
        if not self.config.drop_window_observations or exiting is None or promoted:
            return []
        key = exiting[0]
        return [
            i
            for i in self._graph.factors_of(key)
            if self._graph.is_bearing(i)
            and any(is_landmark_key(k) for k in self._graph.factor_keys(i))
        ]

    def _window_exit(
        self, robot: _Robot, exiting: tuple[int, int] | None
    ) -> tuple[bool, tuple[tuple[int, int], ...]]:
        """Is the pose leaving the window kept as a keyframe, and which poses go."""
        cfg = self.config
        if exiting is None:
            return False, ()
        if cfg.max_keyframes == 0:
            return False, (exiting,)
        if (
            robot.keyframes
            and not self._holds_candidate_ray(exiting[0])
            and self._near_keyframe(robot, exiting[0])
        ):
            return False, (exiting,)
        if len(robot.keyframes) >= cfg.max_keyframes:
            return True, (robot.keyframes[0],)
        return True, ()

    def _near_keyframe(self, robot: _Robot, key: int) -> bool:
        """Is a keyframe near pose `key` (see keyframe_placement): "spacing", its robot's
        last keyframe within keyframe_distance_m and keyframe_angle_rad of it; "area",
        any keyframe of the map within keyframe_distance_m (a bearing sensor sees all
        around: a place is known whichever way the robot faced there)."""
        cfg = self.config
        pose = self._graph.pose(key)
        if cfg.keyframe_placement == "spacing":
            xyt = self._graph.poses_xyt([robot.keyframes[-1][0]])
            turn = np.abs(wrap_angles(xyt[:, 2] - pose.theta())) < cfg.keyframe_angle_rad
        else:
            xyt = self._graph.poses_xyt([k for r in self._robots.values() for k, _ in r.keyframes])
            turn = np.ones(len(xyt), dtype=bool)
        near = np.hypot(xyt[:, 0] - pose.x(), xyt[:, 1] - pose.y()) < cfg.keyframe_distance_m
        return bool(np.any(near & turn))

    def _window_full(self, robot: _Robot) -> bool:
        """Does the robot's oldest window pose leave with this frame (see pose_window and
        SlamConfig.window_factor_bound)?"""
        cfg = self.config
        n = len(robot.window)
        if cfg.pose_window is None or n < cfg.pose_window:
            return False
        bound = cfg.window_factor_bound
        if bound is None or n >= max(cfg.max_pose_window, cfg.pose_window):
            return True
        if self._window_factor_count(robot) >= bound:
            return True
        most = cfg.window_marginals
        return most is not None and self._window_marginals(robot) >= most

    def _window_factor_count(self, robot: _Robot) -> int:
        """Bearing factors on the robot's window poses (see SlamConfig.window_factor_bound)."""
        counts = self._window_factors
        return sum(counts.get(key, 0) for key, _ in robot.window)

    def _window_marginals(self, robot: _Robot) -> int:
        """Marginal factors on the robot's window poses (see SlamConfig.window_marginals)."""
        return self._graph.marginals_touching(key for key, _ in robot.window)

    def _holds_candidate_ray(self, key: int) -> bool:
        """Does a candidate track hold its first ray from pose `key` (and is the option on)?"""
        if not self.config.keyframe_for_candidate_rays:
            return False
        return any(c.rays and c.rays[0].pose_key == key for c in self._candidates.values())

    def _triangulate(
        self, rays: tuple[Ray, ...], current: int, predicted: gtsam.Pose2
    ) -> tuple[Triangulation, tuple[Ray, ...]] | None:
        """Initialise a candidate if its rays pass every sanity check; drop one outlier ray."""
        cfg = self.config
        if len(rays) < cfg.min_rays:
            return None
        xyt = self._graph.poses_xyt([r.pose_key for r in rays if r.pose_key != current])
        here = np.array([predicted.x(), predicted.y(), predicted.theta()])
        mine = np.array([r.pose_key == current for r in rays])
        poses = np.empty((len(rays), 3))
        poses[mine] = here
        poses[~mine] = xyt
        origins = poses[:, :2]
        directions = wrap_angles(poses[:, 2] + np.array([r.bearing_rad for r in rays]))
        sigmas = np.array([r.sigma_rad for r in rays])
        if parallax(directions) < cfg.min_parallax_rad:
            return None
        used = np.ones(len(rays), dtype=bool)
        for _ in range(2):
            if used.sum() < cfg.min_rays:
                return None
            tri = triangulate(origins[used], directions[used], sigmas[used])
            if tri is None or tri.parallax_rad < cfg.min_parallax_rad:
                return None
            worst = int(np.argmax(np.abs(tri.residuals)))
            if abs(tri.residuals[worst]) > cfg.max_residual_sigmas:
                used[np.flatnonzero(used)[worst]] = False
                continue
            if not np.all((tri.depths > cfg.min_depth_m) & (tri.depths <= cfg.max_depth_m)):
                return None
            if math.sqrt(float(np.linalg.eigvalsh(tri.covariance)[-1])) > cfg.max_position_sigma_m:
                return None
            return tri, tuple(r for r, u in zip(rays, used, strict=True) if u)
        return None

    def _commit(
        self,
        frame: FrameInput,
        robot: _Robot | None,
        plan: _Plan,
        before: dict[int, gtsam.Pose2],
    ) -> _Robot:
        """Apply the plan's bookkeeping after iSAM2 accepted the update."""
        frame_index = self._frames
        if robot is None:
            robot = _Robot(
                slot=len(self._robots), last_seq=frame.seq, last_stamp=frame.stamp, next_index=0
            )
            self._robots[frame.robot] = robot
        robot.last_seq = frame.seq
        robot.last_stamp = frame.stamp
        robot.next_index += 1
        robot.motion = None
        robot.tracked = None
        robot.window.append((plan.key, frame_index))
        if self.config.window_factor_bound is not None:  # only a growing window counts
            self._window_factors[plan.key] = len(plan.factored)
            for _, _, rays in plan.new_landmarks:
                for r in rays:
                    if r.pose_key in self._window_factors:
                        self._window_factors[r.pose_key] += 1
        self._apply_exit(robot, plan.exiting, plan.promoted, plan.leaving, before)
        self._trajectory.append(frame_index, robot.slot, frame.seq, frame.stamp, plan.predicted)
        self._live_frames[frame_index] = plan.key

        here = self._graph.pose(plan.key)
        here_xy = np.array([here.x(), here.y()])
        for lid, _ in plan.observed:
            self._landmarks[lid].observe(here_xy, frame.stamp)
        for lid in plan.factored:
            self._last_factor[lid] = frame_index
        self._candidates.update(plan.candidates)
        for label, _, rays in plan.new_landmarks:
            lid = self._next_landmark_id
            self._next_landmark_id += 1
            record = LandmarkRecord(lid, label, frame_index, rays[0].stamp, frame.stamp)
            for r in rays:
                p = self._graph.pose(r.pose_key)
                record.observe(np.array([p.x(), p.y()]), r.stamp)
            self._landmarks[lid] = record
            self._last_factor[lid] = frame_index
            self._label_to_id[label] = lid
            del self._candidates[label]
        for lid, rays in plan.restored:
            self._reinstate(lid, rays, frame_index)
        self._count_frame()
        return robot

    def _reinstate(self, lid: int, rays: tuple[Ray, ...], frame_index: int) -> None:
        """Bookkeeping of an archived landmark back in the graph: its live record again
        (same id, E(X) and count, which its rays extend)."""
        record = self._archive.take(lid, frame_index)
        for r in rays:
            p = self._graph.pose(r.pose_key)
            record.observe(np.array([p.x(), p.y()]), r.stamp)
        self._landmarks[lid] = record
        self._last_factor[lid] = frame_index
        self._label_to_id[record.label] = lid
        self._candidates.pop(record.label, None)
        self.restoration_count += 1

    def _count_frame(self) -> None:
        """One more frame; every _SWEEP_EVERY frames, candidates left unseen expire."""
        self._frames += 1
        if self._frames % _SWEEP_EVERY == 0:
            horizon = self._frames - self.config.candidate_ttl_frames
            for label in [lb for lb, c in self._candidates.items() if c.last_frame < horizon]:
                del self._candidates[label]

    def _poses_before_exit(
        self,
        robot: _Robot | None,
        exiting: tuple[int, int] | None,
        promoted: bool,
        leaving: tuple[tuple[int, int], ...],
    ) -> dict[int, gtsam.Pose2]:
        """Estimates before an update that marginalises `leaving`: what those poses keep,
        and the anchor keyframe of an exiting non-keyframe pose (see _apply_exit)."""
        before = {k: self._graph.pose(k) for k, _ in leaving}
        if robot is not None and robot.keyframes and exiting and not promoted:
            anchor_key = robot.keyframes[-1][0]
            before.setdefault(anchor_key, self._graph.pose(anchor_key))
        return before

    def _apply_exit(
        self,
        robot: _Robot,
        exiting: tuple[int, int] | None,
        promoted: bool,
        leaving: tuple[tuple[int, int], ...],
        before: dict[int, gtsam.Pose2],
    ) -> None:
        """Bookkeeping of the oldest window pose leaving (as a keyframe if `promoted`)
        and of the poses marginalised with it, after the graph's update."""
        anchored_exit = False
        if exiting is not None:
            robot.window.popleft()
            self._window_factors.pop(exiting[0], None)
            if promoted:
                robot.keyframes.append(exiting)
            elif robot.keyframes:
                # A non-keyframe pose follows its keyframe: it keeps its pose relative
                # to the robot's last keyframe, which the graph goes on correcting.
                anchor = robot.keyframes[-1][0]
                rel = before[anchor].between(before[exiting[0]])
                self._set_traj_pose(exiting[1], rel)
                followers = self._anchored.setdefault(anchor, array("q"))
                followers.append(exiting[1])
                # Tracked frames that followed the exiting pose now follow the keyframe.
                for f in self._anchored.pop(exiting[0], ()):
                    self._set_traj_pose(f, rel.compose(self._traj_pose_at(f)))
                    followers.append(f)
                self._live_frames.pop(exiting[1], None)
                anchored_exit = True
        for key, old_frame in leaving:
            if anchored_exit and exiting is not None and key == exiting[0]:
                continue
            if robot.keyframes and robot.keyframes[0][0] == key:
                robot.keyframes.popleft()
            self._retire(key, old_frame, before[key])

    def _shrink_window(self, robot: _Robot) -> None:
        """One more pose leaves a window longer than pose_window whose poses hold more
        than window_factor_bound bearing factors or window_marginals marginal factors
        (+ 5 %, so that this second update is rare): the frame's own exit only keeps the
        window's length, and the factors later added to its poses (a landmark's earlier
        rays, a removed landmark's marginal) or a denser stretch of observations would
        otherwise hold it over the bound."""
        bound, length = self.config.window_factor_bound, self.config.pose_window
        if bound is None or length is None or len(robot.window) <= length:
            return
        most = self.config.window_marginals
        if self._window_factor_count(robot) <= bound + bound // _SHRINK_SLACK and (
            most is None or self._window_marginals(robot) <= most + most // _SHRINK_SLACK
        ):
            return
        self._exit_oldest(robot)

    def _exit_oldest(self, robot: _Robot) -> None:
        """The robot's oldest window pose leaves the window in an update of its own (as a
        keyframe, or marginalised)."""
        exiting = robot.window[0]
        promoted, leaving = self._window_exit(robot, exiting)
        before = self._poses_before_exit(robot, exiting, promoted, leaving)
        drop = self._dropped_observations(exiting, promoted)
        if leaving or drop:  # a pose promoted to keyframe leaves nothing to marginalise
            self._graph.update(marginalise=[k for k, _ in leaving], drop=drop)
        self._apply_exit(robot, exiting, promoted, leaving, before)
        if promoted:
            self._graph.marginal_keys.extend(self._graph.neighbourhoods(exiting[0]))

    def _retire(self, key: int, frame: int, pose: gtsam.Pose2) -> None:
        """A marginalised pose's frame keeps `pose`; frames anchored to it follow."""
        self._live_frames.pop(frame, None)
        self._set_traj_pose(frame, pose)
        followers = self._anchored.pop(key, array("q"))
        for f in followers:
            self._set_traj_pose(f, pose.compose(self._traj_pose_at(f)))
        final = self._trajectory.finalise([frame, *followers])
        if self._trajectory_sink is None:
            self._trajectory.keep(final)
        else:
            self._final_rows.append(pose_rows(final, list(self._robots)))

    def _thin_keyframes(self) -> None:
        """Marginalise the oldest keyframes of any marginal factor that links more than
        max_linked_keyframes of them (see SlamConfig.max_linked_keyframes): a factor
        that grew without a marginalisation (a window pose in it became a keyframe)."""
        bound = self.config.max_linked_keyframes
        linked, self._graph.marginal_keys = self._graph.marginal_keys, []
        if not linked or max(len(k) for k in linked) <= bound:
            return
        owner = self._keyframe_owners()
        if self.config.marginal_sparsification == "chow_liu":
            # Factors whose tree would lose a direction are thinned instead.
            linked = self._graph.sparsify_marginals(linked, self._too_dense(owner))
            self._graph.marginal_keys = []
        drop: set[int] = set()
        for keys in linked:
            drop.update(self._excess_keyframes(keys, owner))
        if drop:
            self._marginalise_with_thinning([], drop, owner, thinning=True)

    def _keyframe_owners(self) -> dict[int, tuple[_Robot, int]]:
        """Every keyframe's key -> (its robot, its frame index)."""
        return {
            key: (robot, frame) for robot in self._robots.values() for key, frame in robot.keyframes
        }

    def _too_dense(self, owner: dict[int, tuple[_Robot, int]]) -> Callable[[Sequence[int]], bool]:
        """Whether a marginal factor over some keys links more than max_linked_keyframes
        of the keyframes `owner` lists (it is then sparsified, see
        SlamConfig.marginal_sparsification)."""
        bound = self.config.max_linked_keyframes
        return lambda keys: len(keys) > bound and sum(k in owner for k in keys) > bound

    def _excess_keyframes(
        self, keys: Iterable[int], owner: dict[int, tuple[_Robot, int]]
    ) -> list[int]:
        """The oldest keyframes among a marginal factor's `keys` beyond max_linked_keyframes
        (down to 3/4 of it, so that thinning is rare)."""
        bound = self.config.max_linked_keyframes
        mine = sorted((k for k in keys if k in owner), key=lambda k: owner[k][1])
        if len(mine) <= bound:
            return []
        return mine[: len(mine) - (3 * bound) // 4]

    def _marginalise_with_thinning(
        self,
        keys: Sequence[int],
        thin: Iterable[int] = (),
        owner: dict[int, tuple[_Robot, int]] | None = None,
        *,
        thinning: bool = False,
    ) -> None:
        """Marginalise `keys` (and the keyframes `thin`) in one update, together with the
        oldest keyframes of every marginal factor it would leave linking more than
        max_linked_keyframes of them.

        Thinning after the update instead (as _thin_keyframes does) means one more
        iSAM2 update per removal, and while it runs iSAM2 still holds the oversized
        factor (a landmark seen from 60 keyframes links all of them): dense copies of it
        in the graph, its linearisation and its root clique, on top of the thinning's
        own. The marginal is the same either way (Schur complements compose), and the
        keyframes are still eliminated on their own, after `keys`, so that their
        marginal is relative as it was (IncrementalGraph.update's then_marginalise).
        With Chow-Liu sparsification the factors are sparsified instead, unless
        `thinning` (a factor whose tree would lose a direction)."""
        owner = self._keyframe_owners() if owner is None else owner
        if self.config.marginal_sparsification == "chow_liu" and not thinning:
            self._graph.update(marginalise=keys, sparsify=self._too_dense(owner))
            return
        marginalise = set(keys)
        drop = set(thin)
        for _ in range(4):  # each round takes in the factors of the keyframes it adds
            marginalise |= drop
            drop = set()
            for span in self._graph.marginal_spans(sorted(marginalise)):
                drop.update(self._excess_keyframes(span, owner))
            if not drop:
                break
        thinned = sorted((k for k in marginalise if k in owner), key=lambda k: owner[k][1])
        poses = {k: self._graph.pose(k) for k in thinned}
        first = sorted(set(keys) - set(thinned))
        self._graph.update(marginalise=first, then_marginalise=thinned)
        for key in thinned:
            robot, frame = owner[key]
            robot.keyframes.remove((key, frame))
            self._retire(key, frame, poses[key])

    def _traj_pose_at(self, frame: int) -> gtsam.Pose2:
        return self._trajectory.pose_at(frame)

    def _set_traj_pose(self, frame: int, pose: gtsam.Pose2) -> None:
        self._trajectory.set_pose(frame, pose)

    def _in_view(self, frame: FrameInput) -> set[int]:
        """Ids of the live landmarks `frame` observed (after its update)."""
        return {
            self._label_to_id[o.label] for o in frame.observations if o.label in self._label_to_id
        }

    def _enforce_budget(self, frame: FrameInput) -> None:
        """Once the live count exceeds the cap, marginalise the policy's choices until it
        is removal_margin below it."""
        cap = self.config.landmark_cap
        if cap is None or len(self._landmarks) <= cap:
            return
        ids = np.array(sorted(self._landmarks), dtype=np.int64)
        records = [self._landmarks[int(i)] for i in ids]
        information = None
        if self._policy.needs_information:
            information = information_content(self.landmark_covariances([int(i) for i in ids]))
        table = LandmarkTable(
            ids=ids,
            observed_from=np.array([r.observed_from for r in records]),
            counts=np.array([r.count for r in records], dtype=np.int64),
            first_seen=np.array([r.added_frame for r in records], dtype=np.int64),
            information=information,
        )
        chosen: list[Removal] = []
        spared = list(self._in_view(frame)) if self.config.spare_observed else []
        # Marginalising a landmark leaves the others' marginals unchanged, so one
        # covariance computation serves every removal of this frame.
        while len(table.ids) > cap - self.config.removal_margin:
            candidates = ~np.isin(table.ids, spared)
            pool = _rows(table, candidates) if spared and candidates.any() else table
            removal = self._policy.select(pool, rng=self._rng)
            chosen.append(removal)
            table = _rows(table, table.ids != removal.landmark_id)
        positions = {r.landmark_id: self.landmark_position(r.landmark_id) for r in chosen}
        covariances = self.landmark_covariances([r.landmark_id for r in chosen])
        self._marginalise_with_thinning([landmark_key(r.landmark_id) for r in chosen])
        for removal, covariance in zip(chosen, covariances, strict=True):
            record = self._landmarks.pop(removal.landmark_id)
            self._last_factor.pop(removal.landmark_id, None)
            del self._label_to_id[record.label]
            pos = positions[removal.landmark_id]
            self._archive.put(
                record,
                position=pos,
                covariance=covariance,
                frame=self._frames - 1,
                stamp=frame.stamp,
                policy=removal.policy,
                reason=removal.reason,
            )
            entry = RemovalRecord(
                frame=self._frames - 1,
                stamp=frame.stamp,
                landmark_id=record.id,
                label=record.label,
                position=(float(pos[0]), float(pos[1])),
                observed_from=(float(record.observed_from[0]), float(record.observed_from[1])),
                count=record.count,
                removal=removal,
            )
            self.removals.append(entry)
            self.removal_count += 1
            self._unreported.append(entry)


def _rows(table: LandmarkTable, keep: NDArray[np.bool_]) -> LandmarkTable:
    """The rows of `table` where `keep` is true."""
    return LandmarkTable(
        ids=table.ids[keep],
        observed_from=table.observed_from[keep],
        counts=table.counts[keep],
        first_seen=table.first_seen[keep],
        information=None if table.information is None else table.information[keep],
    )
