"""The place localiser: one particle filter per robot, the map's places, the status.

Per frame and robot, `Localiser.step` moves the robot's filter by the odometry,
weights it by the labelled bearings to landmarks whose map position is known (the
graph's live landmarks), recognises places, and runs the status machine:

- a robot that arrives without an initial pose is ``initialising``: its filter
  starts from a proposal (positions around the best-recognised places and over the
  map's extent, each heading drawn so that one observed landmark lies at its
  observed bearing); once the filter has been converged for ``confirm_frames``
  frames the status is ``relocalised`` and the step asks the caller to anchor the
  robot's pose chain at the filter's estimate (with its covariance as the prior);
  the next frame is ``tracking``;
- while ``tracking``, the graph's pose and the filter's estimate are compared by
  the Mahalanobis distance under the sum of their covariances; beyond the gate
  for ``lost_frames`` consecutive frames the robot is ``lost`` -- and so it is when
  the filter's fast likelihood average stays far below its slow one (the
  observations stopped fitting the map): the caller stops feeding the graph's
  chain and the filter re-localises as above.

Augmented MCL injects particles from the same proposal when the filter's
likelihood drops (see graph.particles). Pure: no service, no settings; the caller
passes an ``rng``.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from graph.angles import wrap_angles
from graph.particles import FilterConfig, FilterEstimate, Injector, ParticleFilter
from graph.places import LandmarkCandidate, Place, PlaceConfig, PlaceMap, Recognition
from graph.types import Pose2D, restore_fields
from graph.window_check import (
    CONFIRMED,
    REFUTED,
    WAIT,
    WindowCheckConfig,
    WindowFrame,
    check_window,
    rejects_old_pose,
)

FloatArray = NDArray[np.float64]

INITIALISING = "initialising"
TRACKING = "tracking"
LOST = "lost"
RELOCALISED = "relocalised"


def _uniform_poses(n: int, lo: FloatArray, hi: FloatArray, rng: np.random.Generator) -> FloatArray:
    """(n, 3) poses uniform over the box [lo, hi] (x, y) and over all headings."""
    out = np.empty((n, 3))
    out[:, :2] = lo + rng.random((n, 2)) * (hi - lo)
    out[:, 2] = rng.uniform(-math.pi, math.pi, n)
    return out


def _aimed_headings(
    xy: FloatArray,
    landmarks_xy: FloatArray,
    bearings_rad: FloatArray,
    sigma_rad: float,
    rng: np.random.Generator,
) -> FloatArray:
    """(n,) headings (unwrapped) that put one observed landmark, drawn per position, at
    its observed bearing from each position of `xy` (n, 2), with N(0, sigma) noise."""
    j = rng.integers(0, len(bearings_rad), len(xy))
    d = landmarks_xy[j] - xy
    heading: FloatArray = (
        np.arctan2(d[:, 1], d[:, 0]) - bearings_rad[j] + rng.normal(0, sigma_rad, len(xy))
    )
    return heading


@dataclass(frozen=True, slots=True)
class LocaliserConfig:
    filter: FilterConfig = field(default_factory=FilterConfig)
    places: PlaceConfig = field(default_factory=PlaceConfig)
    top_places: int = 3
    """Places the injection proposal draws around (by recognition score)."""
    place_sigma_m: float = 0.75
    """Position spread of proposals around a place's reference position."""
    uniform_share: float = 0.3
    """Share of proposals drawn over the whole map extent even when places are known."""
    heading_sigma_rad: float = math.radians(3.0)
    map_margin_m: float = 1.0
    """The map extent is the landmarks' bounding box grown by this margin."""
    confirm_frames: int = 3
    """Consecutive converged frames before a robot is relocalised."""
    lost_gate: float = 16.27
    """Squared Mahalanobis gate of graph vs filter (chi^2, 3 dof, 99.9 %)."""
    lost_frames: int = 5
    """Consecutive frames beyond the gate before a tracking robot is lost."""
    lost_sigma_floor: tuple[float, float, float] = (0.3, 0.3, math.radians(10.0))
    """Sigmas (m, m, rad) added in quadrature to both covariances in the gate: a map
    a few decimetres off is not a lost robot (graph and filter are both confident and
    each a little wrong); with the default gate, ~1.2 m or ~40 deg of disagreement."""
    lost_likelihood_ratio: float = 0.3
    """Also lost: the filter's fast likelihood average below this share of the slow one
    for lost_frames consecutive frames with observations (the observations no longer fit
    the map around the believed pose -- also when no graph pose is given)."""
    reliability_frames: int = 30
    """Recent frames over which a landmark's dynamic reliability is counted."""
    reliability_floor: float = 0.1
    """Reliability of a mapped landmark not seen lately (a narrow-FOV camera sees few
    directions at a time; the floor keeps places spread over all directions)."""
    learn_places: bool = True
    """Learn a place automatically when far from every place or recognition is weak."""
    # New fields go last: a pickled config is the tuple of its field values, in order.
    hint_heading_sigma_rad: float = 0.1
    """Heading spread of proposals around a hint (see Localiser.proposal)."""
    verify_window: int = 150
    """Frames of a search (labelled bearings and odometry) kept to check a converged
    filter before the robot is relocalised when the caller gives no check of its own
    (see graph.window_check); 0: no check."""
    kidnap_window: int = 30
    """Frames the old-pose test looks back at most (labelled maps; 0: no test): once the
    graph's pose fails to explain a frame's bearings, each frame with observations tests
    the frames since against the graph's pose just before them; the robot is lost when
    they reject it, also without any one landmark's bearings
    (graph.window_check.rejects_old_pose)."""
    kidnap_gate: float = 20.0
    """The old-pose test's statistic beyond which the robot is lost (chi^2, 3 dof)."""
    kidnap_sigma_floor: tuple[float, float, float] = (0.2, 0.2, math.radians(6.0))
    """Sigmas (m, m, rad) added in quadrature to the graph's covariance of the old pose
    in the test: the graph is overconfident about where it tracks a robot, and its
    correcting that is no kidnap. (MRCLAM-6, robot 2 mapping alone: 9 deg of heading
    drift over ten frames without a bearing, corrected as bearings came back, made it
    lost with 0.15 m / 3 deg; 0.3 m / 10 deg missed robot 4 running on with robot 5's
    frames, 1.5 m away.)"""
    kidnap_calm_frames: int = 10
    """Frames with observations the graph's poses explain after which the test stops."""
    kidnap_blind_turn_sigma: float = 0.15
    """Heading sigma (rad per radian) added in quadrature to the old pose in the test for
    the turning the robot did without a bearing just before it: odometry drifts most
    while turning, and the graph, with no bearing to hold it, follows that drift and
    corrects it when bearings return, which is no kidnap. (MRCLAM-6, robot 2 mapping
    alone: 120 deg turned blind, its odometry 28 deg off the truth, corrected within ten
    frames as landmarks came back, made it lost; 0.25 delayed the kidnap of robot 4 in
    robot 1's map from 7 to 17 frames.)"""
    window_check: WindowCheckConfig = field(default_factory=WindowCheckConfig)
    """The check of a converged filter against the search's frames (verify_window)."""

    def __setstate__(self, state: tuple[Any, ...]) -> None:
        restore_fields(self, state)  # also a state pickled before later fields existed


@dataclass(frozen=True, slots=True)
class StepResult:
    status: str
    estimate: FilterEstimate
    place: int | None
    confidence: float
    anchor: bool
    """True on the frame the robot is relocalised: anchor its chain at the estimate."""
    learnt: Place | None = None


@dataclass
class RobotTrack:
    pf: ParticleFilter
    status: str
    converged_frames: int = 0
    disagree_frames: int = 0
    weak_frames: int = 0
    lost_reason: str | None = None
    lost_count: int = 0
    seen: deque[frozenset[str]] = field(default_factory=deque)
    window: deque[WindowFrame] = field(default_factory=deque)
    """The frames of the current search (initialising or lost), for check_window."""
    graph_fit: float = 1.0
    """How well the graph's latest pose explains its frame's bearings, relative to the
    filter's slow likelihood average."""
    history: deque[tuple[WindowFrame, FloatArray, FloatArray, float]] = field(default_factory=deque)
    """The latest tracked frames with the graph's pose (3,) and covariance (3, 3) of each,
    and the radians turned without a bearing up to that pose (0 when its frame has one)."""
    suspect: int = 0
    """Frames since the graph's pose first failed to explain a frame (0: it does)."""
    calm: int = 0
    rejection: float = 0.0
    """The old-pose test's latest statistic."""
    blind_turn: float = 0.0
    """Radians turned (odometry, in absolute value) since the latest frame with a bearing."""
    held: tuple[FloatArray, int] | None = None
    """The window check's confirmed solution and the search's frame count then, while
    it must hold (WindowCheckConfig.stable_frames)."""

    def lose(self, reason: str) -> None:
        """The robot is lost: a fresh search, the tracked frames forgotten."""
        self.status = LOST
        self.lost_reason = reason
        self.lost_count += 1
        self.window.clear()
        self.history.clear()
        self.converged_frames = self.disagree_frames = self.weak_frames = 0
        self.suspect = self.calm = 0
        self.blind_turn = 0.0
        self.held = None

    def __setstate__(self, state: dict[str, Any]) -> None:
        # A track pickled before `window`, `history` or the blind turns existed.
        self.__dict__.update(state)
        self.__dict__.setdefault("window", deque())
        self.__dict__.setdefault("history", deque())
        self.__dict__.setdefault("blind_turn", 0.0)
        self.__dict__.setdefault("held", None)
        self.__dict__.pop("suspect_blind_turn", None)
        self.history = deque(h if len(h) == 4 else (*h, 0.0) for h in self.history)


def _held(
    track: RobotTrack,
    solved: FloatArray,
    frames: Sequence[WindowFrame],
    hold: int,
    cfg: LocaliserConfig,
) -> str:
    """CONFIRMED once the check's solution has held for `hold` frames (see
    WindowCheckConfig.stable_frames), else WAIT; `frames` is the search's window."""
    n = len(frames)
    if n >= cfg.verify_window:  # the window slides: the held frame's place is gone
        track.held = None
        return CONFIRMED
    if track.held is None or track.held[1] > n:
        track.held = (np.asarray(solved, dtype=np.float64), n)
        return WAIT
    first, since = track.held
    if n - since < hold:
        return WAIT
    moved = gtsam.Pose2(*first)
    for f in frames[since:]:
        if f.odometry is not None:
            moved = moved.compose(gtsam.Pose2(*f.odometry))
    dx = float(np.hypot(solved[0] - moved.x(), solved[1] - moved.y()))
    dtheta = abs(float(wrap_angles(solved[2] - moved.theta())))
    tol_m, tol_rad = cfg.window_check.stable_tolerance
    if dx <= tol_m and dtheta <= tol_rad:
        track.held = None
        return CONFIRMED
    track.held = (np.asarray(solved, dtype=np.float64), n)
    return WAIT


def _bounds(landmarks: Mapping[str, FloatArray], margin: float) -> tuple[float, ...]:
    xy = np.array(list(landmarks.values()), dtype=np.float64).reshape(-1, 2)
    if len(xy) == 0:
        return (-margin, -margin, margin, margin)
    lo, hi = xy.min(axis=0) - margin, xy.max(axis=0) + margin
    return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))


@dataclass
class Localiser:
    """Filters per robot and the map's places (see the module docstring)."""

    config: LocaliserConfig = field(default_factory=LocaliserConfig)
    places: PlaceMap = field(default_factory=PlaceMap)
    robots: dict[str, RobotTrack] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.places.places:
            self.places = PlaceMap(self.config.places)

    # ------------------------------------------------------------ proposals
    def proposal(
        self,
        recognition: Recognition,
        landmarks_xy: FloatArray,
        bearings_rad: FloatArray,
        bounds: Sequence[float],
        hints: Sequence[tuple[FloatArray, float]] | None = None,
    ) -> Injector:
        """Poses around the top-ranked places (and over the map extent), each heading
        such that one observed landmark lies at its observed bearing.

        `hints`: (pose (3,), weight > 0) of places recognised by another route (a camera
        map's appearance places: position and heading, the place's heading turned by the
        recognised yaw offset); they replace the labelled places' ranking, and their
        draws keep the hint's heading (a pose-free match may be wrong; the appearance
        yaw is not)."""
        cfg = self.config
        if hints:
            return self._hinted_proposal(hints, landmarks_xy, bearings_rad, bounds)
        # A place draws proposals by how much better it scores than a typical place (the
        # median): a frame that every place explains alike (one landmark seen, which many
        # places hold) says nothing about where the robot is, and the proposal stays
        # uniform instead of favouring whichever places rank first among equals.
        scores_all = np.asarray(recognition.scores, dtype=np.float64)
        baseline = float(np.median(scores_all)) if len(scores_all) else 0.0
        excess = np.maximum(scores_all - baseline, 0.0)
        ranked = [
            (int(p), float(e), float(d))
            for p, e, d in zip(
                recognition.place_ids[: cfg.top_places],
                excess[: cfg.top_places],
                recognition.yaw_offsets_rad[: cfg.top_places],
                strict=True,
            )
            if e > 0
        ]
        top = float(scores_all[0]) if len(scores_all) else 0.0
        place_share = (1.0 - cfg.uniform_share) * (float(excess[0]) / top if top > 0 else 0.0)
        lo = np.array(bounds[:2], dtype=np.float64)
        hi = np.array(bounds[2:], dtype=np.float64)
        places = self.places.places

        def draw(n: int, rng: np.random.Generator) -> FloatArray:
            out = np.empty((n, 3))
            n_place = round(n * place_share) if ranked else 0
            out[n_place:] = _uniform_poses(n - n_place, lo, hi, rng)
            if n_place:
                scores = np.array([s for _, s, _ in ranked])
                pick = rng.choice(len(ranked), size=n_place, p=scores / scores.sum())
                ref = np.array(
                    [
                        [places[p].pose.x, places[p].pose.y, places[p].pose.theta - d]
                        for p, _, d in ranked
                    ]
                )[pick]
                out[:n_place, :2] = ref[:, :2] + rng.normal(0, cfg.place_sigma_m, (n_place, 2))
                out[:n_place, 2] = ref[:, 2] + rng.normal(0, 0.3, n_place)
            if len(bearings_rad):
                out[:, 2] = _aimed_headings(
                    out[:, :2], landmarks_xy, bearings_rad, cfg.heading_sigma_rad, rng
                )
            out[:, 2] = wrap_angles(out[:, 2])
            return out

        return draw

    def _hinted_proposal(
        self,
        hints: Sequence[tuple[FloatArray, float]],
        landmarks_xy: FloatArray,
        bearings_rad: FloatArray,
        bounds: Sequence[float],
    ) -> Injector:
        cfg = self.config
        refs = np.array([np.asarray(p, dtype=np.float64) for p, _ in hints]).reshape(-1, 3)
        weights = np.array([max(float(w), 0.0) for _, w in hints])
        share = 1.0 - cfg.uniform_share if weights.sum() > 0 else 0.0
        p = weights / weights.sum() if weights.sum() > 0 else None
        lo = np.array(bounds[:2], dtype=np.float64)
        hi = np.array(bounds[2:], dtype=np.float64)

        def draw(n: int, rng: np.random.Generator) -> FloatArray:
            out = np.empty((n, 3))
            n_hint = round(n * share)
            out[n_hint:] = _uniform_poses(n - n_hint, lo, hi, rng)
            if len(bearings_rad) and n > n_hint:
                out[n_hint:, 2] = _aimed_headings(
                    out[n_hint:, :2], landmarks_xy, bearings_rad, cfg.heading_sigma_rad, rng
                )
            if n_hint:
                ref = refs[rng.choice(len(refs), size=n_hint, p=p)]
                out[:n_hint, :2] = ref[:, :2] + rng.normal(0, cfg.place_sigma_m, (n_hint, 2))
                out[:n_hint, 2] = ref[:, 2] + rng.normal(0, cfg.hint_heading_sigma_rad, n_hint)
            out[:, 2] = wrap_angles(out[:, 2])
            return out

        return draw

    # ------------------------------------------------------------ the step
    def step(
        self,
        robot: str,
        *,
        odometry: Sequence[float] | None,
        dt_s: float,
        labels: Sequence[str],
        bearings_rad: Sequence[float],
        landmarks: Mapping[str, FloatArray],
        graph_pose: tuple[FloatArray, FloatArray] | None,
        rng: np.random.Generator,
        quality: Sequence[float] | None = None,
        frame: int = -1,
        stamp: float = 0.0,
        covariances: Callable[[], Mapping[str, FloatArray]] | None = None,
        ids: Mapping[str, int] | None = None,
        sigmas_rad: Sequence[float | None] | None = None,
        hints: Sequence[tuple[FloatArray, float]] | None = None,
        verify: Callable[[FilterEstimate], bool] | None = None,
    ) -> StepResult:
        """One frame of one robot.

        `landmarks` maps label -> map position (2,) of the landmarks the filter may use;
        `graph_pose` is (pose (3,), covariance (3, 3), map frame) of the graph's estimate
        for this frame, or None while the graph does not track the robot (initialising,
        lost). `ids` maps labels to landmark ids; `covariances` gives the landmarks'
        (2, 2) covariances when a place is learnt (computed only then); `sigmas_rad`
        each observation's own bearing sigma (None: not stated); `hints` places
        recognised by another route for the injection proposal (see `proposal`);
        `verify` checks a converged estimate before the robot is relocalised at it (False:
        the filter starts a fresh search instead).
        """
        cfg = self.config
        known = [i for i, label in enumerate(labels) if label in landmarks]
        lm_xy = np.array([landmarks[labels[i]] for i in known], dtype=np.float64).reshape(-1, 2)
        z = np.array([bearings_rad[i] for i in known], dtype=np.float64)
        q = None if quality is None else np.array([quality[i] for i in known])
        sig = None
        if sigmas_rad is not None:
            sig = np.array([np.nan if sigmas_rad[i] is None else sigmas_rad[i] for i in known])
        track = self.robots.get(robot)
        current = self.places.last_visited.get(robot)
        if track is not None and track.status != TRACKING:
            current = None  # lost or initialising: no prior from the last place
        recognition = self.places.recognise(
            [labels[i] for i in known], z.tolist(), None if q is None else q.tolist(),
            current=current,
        )  # fmt: skip
        bounds = _bounds(landmarks, cfg.map_margin_m)
        injector = self.proposal(recognition, lm_xy, z, bounds, hints)
        if track is None:
            if graph_pose is not None:
                pf = ParticleFilter.around(
                    graph_pose[0],
                    (0.05, 0.05, math.radians(2.0)),
                    cfg.filter,
                    rng=rng,
                    n=cfg.filter.min_particles,
                )
                track = RobotTrack(pf, TRACKING)
            else:
                pf = ParticleFilter.from_poses(injector(cfg.filter.max_particles, rng), cfg.filter)
                track = RobotTrack(pf, INITIALISING)
            self.robots[robot] = track
        elif odometry is not None:
            track.pf.predict(np.asarray(odometry, dtype=np.float64), dt_s=dt_s, rng=rng)
        if len(z):
            track.pf.update(lm_xy, z, q, rng=rng, injector=injector, sigmas_rad=sig)
        est = track.pf.estimate()
        track.seen.append(frozenset(labels))
        while len(track.seen) > cfg.reliability_frames:
            track.seen.popleft()
        if track.status in (INITIALISING, LOST) and cfg.verify_window > 0:
            sigmas = track.pf.bearing_sigmas(len(z), sig)
            odo = None if odometry is None else np.asarray(odometry, dtype=np.float64)
            track.window.append(WindowFrame(odo, dt_s, lm_xy, z, sigmas))
            while len(track.window) > cfg.verify_window:
                track.window.popleft()

        anchor = False
        if track.status == RELOCALISED:
            track.status = TRACKING
        if track.status == TRACKING and len(z):
            weak = track.pf.w_fast < cfg.lost_likelihood_ratio * track.pf.w_slow
            if (
                weak
                and graph_pose is not None
                and track.pf.fit(graph_pose[0], lm_xy, z, q, sigmas_rad=sig)
                >= cfg.lost_likelihood_ratio * track.pf.w_slow
            ):
                # The graph's pose explains what the robot sees: the filter, not the
                # robot, has lost track (e.g. one bearing a frame while turning on the
                # spot). It starts again around the graph's estimate.
                track.pf = _around_graph(graph_pose, cfg.filter, rng)
                est = track.pf.estimate()
                weak = False
            track.weak_frames = track.weak_frames + 1 if weak else 0
            if graph_pose is not None:
                track.graph_fit = track.pf.fit(graph_pose[0], lm_xy, z, q, sigmas_rad=sig) / max(
                    track.pf.w_slow, 1e-300
                )
        rejected = False
        if track.status == TRACKING and graph_pose is not None and q is None:
            seen = [labels[i] for i in known]
            rejected = self._old_pose_test(
                track, graph_pose, odometry, dt_s, seen, lm_xy, z, sig, est
            )
        if track.status == TRACKING and track.weak_frames >= cfg.lost_frames:
            # The belief no longer explains what the robot sees: search afresh.
            track.lose("observations no longer fit the map")
            track.pf = ParticleFilter.from_poses(
                injector(cfg.filter.max_particles, rng), cfg.filter
            )
            est = track.pf.estimate()
        elif rejected:
            # The frames since the graph's pose stopped explaining them reject the pose
            # the robot was tracked at: it was moved. The filter keeps its hypotheses.
            track.lose("the observations reject the tracked pose")
        elif track.status == TRACKING and graph_pose is not None:
            e = np.asarray(graph_pose[0], dtype=np.float64) - est.pose_xytheta
            e[2] = float(wrap_angles(e[2]))
            s = (
                np.asarray(graph_pose[1], dtype=np.float64)
                + est.covariance
                + np.diag(np.square(cfg.lost_sigma_floor))
            )
            d2 = float(e @ np.linalg.solve(s, e))
            # Only a converged filter disagrees: one whose weight is split between modes
            # (injected hypotheses that a single bearing cannot tell apart) has no pose to
            # disagree with, and its main mode can flip between frames.
            beyond = d2 > cfg.lost_gate and est.converged
            track.disagree_frames = track.disagree_frames + 1 if beyond else 0
            if track.disagree_frames >= cfg.lost_frames:
                track.lose("graph and filter disagree")
        elif track.status in (INITIALISING, LOST):
            # Only frames with observations confirm: without, the belief just drifts.
            if not est.converged:
                track.converged_frames = 0
            elif len(z):
                track.converged_frames += 1
            verdict = None
            if track.converged_frames >= cfg.confirm_frames:
                verdict = self._verdict(track, est, verify, labelled=q is None)
            if verdict == CONFIRMED:
                track.status = RELOCALISED
                track.converged_frames = 0
                track.window.clear()
                anchor = True
            elif verdict == REFUTED:
                # The caller's check refused the pose (the observations fit it only by
                # chance): search afresh rather than converge on it again.
                track.converged_frames = 0
                track.pf = ParticleFilter.from_poses(
                    injector(cfg.filter.max_particles, rng), cfg.filter
                )
                est = track.pf.estimate()

        place, confidence = recognition.best, recognition.best_score
        learnt = None
        if track.status in (TRACKING, RELOCALISED):
            near, dist = self.places.nearest(est.pose_xytheta[:2])
            if near is not None and dist <= cfg.places.learn_distance_m:
                place = near
                self.places.visit(robot, near)
            if cfg.learn_places and self.places.should_learn(
                est.pose_xytheta[:2], recognition.best_score
            ):
                learnt = self.learn(
                    robot,
                    est.pose_xytheta,
                    landmarks,
                    frame=frame,
                    stamp=stamp,
                    covariances=None if covariances is None else covariances(),
                    ids=ids,
                )
                if learnt is not None:
                    place = learnt.id
        if track.status in (INITIALISING, LOST):
            confidence = min(confidence, float(est.converged))
        return StepResult(track.status, est, place, confidence, anchor, learnt)

    def _old_pose_test(
        self,
        track: RobotTrack,
        graph_pose: tuple[FloatArray, FloatArray],
        odometry: Sequence[float] | None,
        dt_s: float,
        observed: Sequence[str],
        lm_xy: FloatArray,
        z: FloatArray,
        sig: FloatArray | None,
        est: FilterEstimate,
    ) -> bool:
        """Keep the tracked frames' history and run the old-pose test (see
        LocaliserConfig.kidnap_window): True when the frames since the graph's pose
        first failed to explain one reject the graph's pose just before them."""
        cfg = self.config
        if cfg.kidnap_window <= 0:
            return False
        misfit = len(z) > 0 and track.graph_fit < cfg.lost_likelihood_ratio
        odo = None if odometry is None else np.asarray(odometry, dtype=np.float64)
        if track.suspect:
            track.suspect += 1
        elif misfit and track.history:
            # The old pose is the previous frame's.
            track.suspect, track.calm = 1, 0
        turned = 0.0 if odo is None else abs(float(odo[2]))
        track.blind_turn = 0.0 if len(z) else track.blind_turn + turned
        sigmas = track.pf.bearing_sigmas(len(z), sig)
        frame = WindowFrame(odo, dt_s, lm_xy, z, sigmas, tuple(observed))
        pose = np.asarray(graph_pose[0], dtype=np.float64)
        cov = np.asarray(graph_pose[1], dtype=np.float64)
        track.history.append((frame, pose, cov, track.blind_turn))
        while len(track.history) > cfg.kidnap_window + 1:
            track.history.popleft()
        if not track.suspect or not len(z):
            return False
        track.calm = 0 if misfit else track.calm + 1
        if track.calm >= cfg.kidnap_calm_frames:
            track.suspect = track.calm = 0
            return False
        n = min(track.suspect, len(track.history) - 1)
        recent = list(track.history)[-n - 1 :]
        _, anchor, anchor_cov, blind = recent[0]
        # The old pose's heading is as unsure as the turn made blind around it: up to it,
        # and on from it until the first frame with a bearing (the test's odometry
        # carries the old pose's heading there unchecked).
        for later, _, _, turned_blind in recent[1:]:
            if len(later.bearings_rad):
                break
            blind = turned_blind
        floor = np.diag(np.square(cfg.kidnap_sigma_floor))
        floor[2, 2] += (cfg.kidnap_blind_turn_sigma * blind) ** 2
        rejected, track.rejection = rejects_old_pose(
            anchor,
            anchor_cov + floor,
            [f for f, _, _, _ in recent[1:]],
            cfg.filter,
            cfg.kidnap_gate,
            latest_xytheta=[est.pose_xytheta],
        )
        return rejected

    def _verdict(
        self,
        track: RobotTrack,
        est: FilterEstimate,
        verify: Callable[[FilterEstimate], bool] | None,
        *,
        labelled: bool,
    ) -> str:
        """CONFIRMED, REFUTED or WAIT (see graph.window_check) for a converged filter:
        the caller's check if it gives one, else (labelled bearings) the window check."""
        if verify is not None:
            return CONFIRMED if verify(est) else REFUTED
        if not labelled or self.config.verify_window <= 0 or not track.window:
            return CONFIRMED
        frames = list(track.window)
        cfg = self.config
        checked = check_window(
            est.pose_xytheta, est.covariance, frames, cfg.filter, cfg.window_check
        )
        hold = cfg.window_check.stable_frames
        if checked.verdict != CONFIRMED or hold <= 0:
            track.held = None
            return checked.verdict
        return _held(track, checked.pose_xytheta, frames, hold, cfg)

    def learn(
        self,
        robot: str,
        pose_xytheta: FloatArray,
        landmarks: Mapping[str, FloatArray],
        *,
        frame: int,
        stamp: float,
        covariances: Mapping[str, FloatArray] | None = None,
        ids: Mapping[str, int] | None = None,
    ) -> Place | None:
        """Learn a place at `pose_xytheta` from the mapped landmarks; reliability from the
        robot's recent frames (floored, see LocaliserConfig.reliability_floor)."""
        cfg = self.config
        track = self.robots.get(robot)
        recent = list(track.seen) if track is not None else []
        candidates = []
        for label, xy in landmarks.items():
            share = sum(label in s for s in recent) / len(recent) if recent else 0.0
            cov = (
                covariances[label]
                if covariances is not None and label in covariances
                else np.eye(2) * 0.01
            )
            candidates.append(
                LandmarkCandidate(
                    label,
                    -1 if ids is None else ids.get(label, -1),
                    (float(xy[0]), float(xy[1])),
                    np.asarray(cov, dtype=np.float64),
                    max(cfg.reliability_floor, share),
                )
            )
        pose = Pose2D(*(float(v) for v in pose_xytheta))
        place = self.places.learn(pose, candidates, robot=robot, frame=frame, stamp=stamp)
        if place is not None:
            self.places.visit(robot, place.id)
        return place

    def forget_robot(self, robot: str) -> None:
        self.robots.pop(robot, None)


def _around_graph(
    graph_pose: tuple[FloatArray, FloatArray], config: FilterConfig, rng: np.random.Generator
) -> ParticleFilter:
    """A fresh filter of the minimum size around the graph's pose ``(3,)``, spread by the
    graph's marginal sigmas (its ``(3, 3)`` covariance; at least 5 cm and 2 degrees)."""
    spread = np.sqrt(np.clip(np.diag(np.asarray(graph_pose[1], dtype=np.float64)), 0, None))
    sigmas = np.maximum(spread, (0.05, 0.05, math.radians(2.0)))
    return ParticleFilter.around(
        np.asarray(graph_pose[0], dtype=np.float64),
        (float(sigmas[0]), float(sigmas[1]), float(sigmas[2])),
        config,
        rng=rng,
        n=config.min_particles,
    )
