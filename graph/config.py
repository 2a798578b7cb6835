"""Parameters of one map's estimator. Plain dataclass: no settings, no environment."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, get_args

Optimizer = Literal["dogleg", "gauss_newton"]
"""The iSAM2 step (see SlamConfig.optimizer)."""
BearingLoss = Literal["huber", "geman_mcclure"]
"""The robust loss of bearing factors (see SlamConfig.bearing_loss)."""
MarginalSparsification = Literal["thin_keyframes", "chow_liu"]
"""How marginal factors are kept sparse (see SlamConfig.marginal_sparsification)."""
KeyframePlacement = Literal["spacing", "area"]
"""Which keyframes a pose leaving the window is compared with (see
SlamConfig.keyframe_placement)."""
Upkeep = Literal["in_frame", "budget_after_frame", "after_frame"]
"""When the work that keeps a map bounded runs (see SlamConfig.upkeep)."""


@dataclass(frozen=True, slots=True)
class SlamConfig:
    """Estimator parameters; units SI (metres, radians) unless a name says otherwise."""

    landmark_cap: int | None = 50
    """Most live landmarks kept in the graph; None = uncapped."""
    policy: str = "coverage"
    """Name of the landmark-selection policy (see graph.policies)."""
    pose_window: int | None = 100
    """Poses kept per robot; older ones are marginalised. None = keep every pose. With
    window_factor_bound the window grows beyond this while its poses hold few factors."""
    bearing_sigma_rad: float = math.radians(1.0)
    """Default one-sigma bearing noise when an observation gives none."""
    huber_k: float | None = 1.345
    """Threshold (huber) or scale (geman_mcclure) of the bearing loss in sigmas; None =
    plain Gaussian."""
    bearing_loss: BearingLoss = "huber"
    """Robust loss of bearing factors in the graph. Huber's pull on a wrong match never
    fades: past the threshold every outlier still tugs with the same force.
    Geman-McClure's weight falls as 1/e^4, so a run of wrong matches (a landmark whose
    corner went out of sight, matched to a look-alike for 40 frames) stops counting once
    it disagrees with the rest. Replaying a rendered run's recorded observations (1000
    frames, cap 200), ATE 0.0377 -> 0.0115 m with scale 1; on the oracle's (no wrong
    matches) 0.0050 -> 0.0056 m. Non-convex: bearings that disagree with a drifted map
    at first (a loop closure after a long way) count for little, so it suits dense,
    frequent observations (cameras), not sparse ones. A tracked frame's pose solve
    (graph.tracking) keeps Huber's at huber_k: it starts from the odometry's prediction,
    where a run's bearings may all be several sigmas off, and Geman-McClure would barely
    let them move it (on the rendered runs it changed ATE by +0-3 %)."""
    odometry_sigma_floor: tuple[float, float, float] = (0.002, 0.002, math.radians(0.2))
    """Odometry sigma (x m, y m, theta rad) of a motionless step."""
    odometry_sigma_per_metre: tuple[float, float, float] = (0.03, 0.03, math.radians(1.0))
    """Odometry sigma growth per metre travelled (x, y, theta)."""
    odometry_sigma_per_radian: float = 0.02
    """Heading sigma growth per radian turned."""
    odometry_sigma_per_sqrt_metre: tuple[float, float, float] = (0.05, 0.05, math.radians(2.0))
    """Random-walk growth with the distance travelled (x m, y m, theta rad per sqrt(m)):
    the variance grows by this squared per metre, however many frames the metre is cut
    into. Added in quadrature to the other terms. The per-metre and per-radian sigmas
    above add per *frame*, so at a high frame rate they sum to little (a 2.5 Hz robot at
    0.06 m/s gets 1 deg of heading sigma over 10 s from them, where MRCLAM's wheel
    odometry drifts 6 deg): the random-walk terms are what keeps the default model
    sound whatever the rate."""
    odometry_sigma_per_sqrt_radian: float = math.radians(5.0)
    """Heading random-walk growth with the angle turned (rad per sqrt(rad)): wheel slip
    while turning, the main heading error of a differential drive (MRCLAM: ~4.5-5.5
    deg per sqrt(rad) fitted against ground truth over 10 s spans)."""
    odometry_sigma_per_sqrt_second: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Random-walk growth (x m, y m, theta rad per sqrt(s)) with the time between frames:
    drift that accrues while the robot is on the move or standing (e.g. heading bias of
    wheel odometry). Added in quadrature to the motion-based sigmas."""
    initial_pose_sigma: tuple[float, float, float] = (0.01, 0.01, math.radians(0.5))
    """Sigma of the prior placed from a robot's initial_pose."""
    landmark_prior_sigma_m: float | None = 5.0
    """Weak prior on each new landmark at its triangulated position; None = none."""
    min_rays: int = 3
    """Rays a candidate needs before it is triangulated."""
    max_rays: int = 40
    """Most rays a candidate keeps (the oldest dropped first, but for candidate_first_rays)."""
    candidate_first_rays: int = 3
    """The first rays of a candidate kept until it initialises, whatever max_rays drops,
    and given bearing factors then (while their poses are in the graph) even when the
    triangulation, which checks the rays against the current estimate, finds them off:
    a robot's first frames are the ones its initial pose anchors, and a landmark seen
    there but initialised hundreds of frames later (too little parallax until then) is
    what ties the map to that frame. Without them MRCLAM-6 robot 3's map was built in
    the frame of its dead reckoning at its first initialised landmark (frame 136) and
    ended 10-12 deg off the initial pose; the batch over every ray, 0.07 deg."""
    min_parallax_rad: float = math.radians(5.0)
    """Smallest spread of ray directions that counts as enough parallax."""
    min_depth_m: float = 0.2
    """Nearest a triangulated landmark may lie from every pose that saw it, metres."""
    max_depth_m: float = 15.0
    """Farthest a triangulated landmark may lie from every pose that saw it, metres. Suits
    rooms and the MRCLAM-6 hall; an outdoor map with landmarks tens of metres away needs
    more (and then a larger max_position_sigma_m: a far landmark's depth is uncertain)."""
    max_residual_sigmas: float = 4.0
    """Largest bearing residual of a triangulation, in sigmas."""
    max_position_sigma_m: float = 0.3
    """Largest one-sigma position error of a triangulated landmark."""
    candidate_ttl_frames: int = 200
    """A candidate not observed for this many frames (of any robot) expires."""
    restore_archived: bool = True
    """A removed landmark seen again by label comes back from the archive under its own
    id, initialised at its archived estimate at once (graph.archive); False: it is a
    new candidate track, re-triangulated under a new id (it stays archived under the old)."""
    restore_after_frames: int = 200
    """Hysteresis: a landmark removed fewer than this many frames ago comes back only
    once it was observed restore_min_rays times since (0: at its first observation).
    Without it a landmark the policy has just judged least useful comes straight back
    and is removed again: MRCLAM-6 robot 2 at cap 8 (information policy) made 1230
    removals in 2229 frames and took twice the CPU time; with 200 frames / 10 rays, 124
    (docs/measurements/archive.md)."""
    restore_min_rays: int = 10
    restore_backoff: bool = False
    """Each removal of a landmark doubles its hysteresis: removed k times, it comes back
    only after restore_after_frames * 2^(k-1) frames or restore_min_rays * 2^(k-1)
    observations. A landmark in view of dense frames (~25 bearings a frame) meets a
    fixed restore_min_rays within a second and churns: on the dense lifelong world,
    19 707 removals in 10 000 frames without it, 1 055 with it. Off by default: at cap 8
    on MRCLAM-6 it made the coverage policy's mean ATE 0.389 m against 0.305 (worse on
    four of five robots; docs/measurements/lifelong.md)."""
    restore_prior_sigma_m: float = 5.0
    """Weak prior (isotropic, metres) at the archived estimate on a restored landmark:
    with a single bearing a landmark is unobservable along the ray, and this keeps
    the graph well-posed. Deliberately weak: the archived covariance's information is
    already in the marginal its removal left on the poses (see BearingSlam)."""
    optimizer: Optimizer = "gauss_newton"
    """iSAM2 step: 'gauss_newton' (partial updates: only the variables whose delta moved
    beyond the wildfire threshold) or 'dogleg' (Powell's trust region). Dogleg's step
    evaluates every factor's error at the linearisation point and at each trial point,
    and the relative marginals are Python factors: on the dense lifelong world that was
    most of a frame's cost (median 149 ms against 77 over the first 1 000 frames, same
    load). On MRCLAM-6 at cap 8 (coverage) it also let a landmark that its window saw
    along one ray only slide along it, unobserved, by 2.4-5.6 m, flipping from one
    side to the other at every update (robot 5, frames 1 984-2 214): live-landmark RMSE
    0.997 m against 0.479 with Gauss-Newton, mean ATE 0.276 against 0.293 m
    (docs/estimator.md). An early Gauss-Newton (before the relative marginals and
    the innovation gate) threw robot 5 off for good (2.57 m ATE)."""
    relinearize_threshold: float = 0.01
    """iSAM2 relinearises a variable whose linear delta exceeds this (metres or radians,
    per component); 0 = every variable at every relinearisation."""
    relinearize_skip: int = 1
    """iSAM2 checks for relinearisation every this many updates (with upkeep
    "after_frame": every this many upkeeps)."""
    relinearise_budget: int | None = 40
    """With an upkeep after the frame (not "in_frame", where it does nothing): the most
    relative marginal factors (graph.relative, evaluated in Python) one iSAM2 update
    relinearises; None: no limit. When the variables past the relinearisation threshold
    touch more, those that moved farthest go first and the others keep their
    linearisation point; the upkeep relinearises them once the frame's answer is sent,
    after its removals. A loop correction's relinearisation (every marginal factor on
    the moved poses re-evaluated in Python) then no longer lands on the frame's answer.
    On MRCLAM-6 at cap 8 (coverage) a budget of 40 holds variables back in 0-527 of a
    robot's 1 376-2 498 frames; without the upkeep's catch-up (held variables waiting for
    later frames) robot 5's ATE went from 0.308 to 0.394 m, with it 0.269."""
    upkeep: Upkeep = "budget_after_frame"
    """When the work that keeps the map bounded runs. "in_frame": all inside
    `BearingSlam.process`. "budget_after_frame": the landmark budget's removals, a second
    window exit and keyframe thinning run in `BearingSlam.upkeep()`, which the service
    calls once the frame's result is sent (and `process` calls first when nobody did).
    "after_frame": iSAM2's relinearisation moves there too; the frame's own update then
    only re-eliminates the cliques it touched, and its pose is the Gauss-Newton step from
    the last upkeep's linearisation point (relinearize_skip counts upkeeps).
    With either of the last two, a frame's outcome reports the removals made after the
    frame before it, and between a frame and its upkeep the map may hold that frame's
    new landmarks above the cap. On the dense lifelong world the removals (19-24 when a
    robot re-enters a room it mapped) and the relinearisations after a loop correction
    (every marginal factor on the moved poses re-evaluated in Python, 35-50 ms against a
    median frame of ~10 ms) are the frames of the tail. "budget_after_frame" is the
    default: without relinearise_budget its map is the "in_frame" one, bit for bit (the
    same updates in the same order; only the frame's answer comes before the removals),
    and with it a loop correction's relinearisation leaves the frame too."""
    window_exit_after_frame: bool = False
    """With an upkeep after the frame (not "in_frame"): the pose leaving a robot's window
    with a frame leaves in the upkeep, not in the frame's update, and the upkeep's
    updates keep the robot's latest pose and the landmarks its frame saw at the Bayes
    tree's root (graph.isam.IncrementalGraph.root_keys), where the next frame's factors
    land. Marginalising the leaving pose reaches the tree's old part, where the removed
    landmarks' marginals are; without it the frame's answer no longer waits for that.
    The window holds one more pose between a frame and its upkeep. Opt-in; its figures
    (dense lifelong world, MRCLAM-6) are in docs/measurements/lifelong.md and
    docs/measurements.md."""
    relative_marginals: bool = True
    """Marginals of old poses are kept relative to the next pose (see graph.relative)
    rather than as linear factors in absolute coordinates."""
    relative_landmark_marginals: bool = True
    """A removed landmark's marginal is kept relative to its oldest pose too (see
    graph.relative), rather than as a linear factor in absolute coordinates whose
    Jacobians stay frozen where the landmark was removed. MRCLAM-6 at cap 8 (policy
    information): robot 1 ATE 0.547 -> 0.403 m, robot 5 0.550 -> 0.378."""
    keyframe_distance_m: float = 0.3
    """A pose leaving the window stays in the graph as a keyframe when no keyframe lies
    within this distance of it (and, with keyframe_placement "spacing", within
    keyframe_angle_rad of its heading; which keyframes: keyframe_placement)."""
    keyframe_angle_rad: float = math.radians(15.0)
    """With keyframe_placement "spacing", a keyframe that turned this far from a pose
    leaving the window is not near it (see keyframe_distance_m)."""
    keyframe_placement: KeyframePlacement = "spacing"
    """Which keyframes a pose leaving the window is compared with (see
    keyframe_distance_m): "spacing", its robot's last keyframe (a robot adds one every
    keyframe_distance_m it travels or keyframe_angle_rad it turns; max_keyframes
    marginalises the oldest); "area", every keyframe of the map, by position only, so
    that keyframes grow with the area explored, not with time (a robot going round the
    same room adds none). "area" keeps fewer poses and costs accuracy: MRCLAM-6 robot 2
    uncapped 0.180 m ATE against 0.159 (robot 1: 80 keyframes against 108), and on the
    dense lifelong world at cap 50 (Chow-Liu sparsification) it reached max_keyframes
    (300) by frame 4 000 as well, ATE 0.270 m against 0.196 (docs/estimator.md)."""
    max_keyframes: int = 300
    """Keyframes kept per robot beyond the window (oldest marginalised first); 0 = none."""
    max_linked_keyframes: int = 24
    """At most this many keyframes in one marginal factor. Marginalising a landmark
    links every pose that saw it, and those links accumulate into one dense factor
    over all keyframes; beyond this bound the oldest keyframes in it are
    marginalised too (down to 3/4 of it), so the dense part of the graph stays small.
    With marginal_sparsification "chow_liu" the factor is sparsified instead."""
    marginal_sparsification: MarginalSparsification = "thin_keyframes"
    """What a marginal factor linking more than max_linked_keyframes keyframes becomes:
    "thin_keyframes" marginalises its oldest keyframes (map detail is lost);
    "chow_liu" replaces it by its Chow-Liu tree (graph.sparsify), one binary factor per
    tree edge, and keeps every keyframe (bounded by max_keyframes and their spacing);
    a factor whose tree would lose a direction it observes is thinned instead. Chow-Liu
    meets the dense lifelong world's tail goal where thinning does not (a thinned
    keyframe's dense marginal is re-eliminated by later updates: p99 5-11x the median),
    but costs accuracy elsewhere: on the 20 000-frame lifelong world the map's shape
    (aligned ATE 0.150 m against 0.112, both in the frame), on MRCLAM-6 at cap 8 the live
    landmarks (1.39x the batch's RMSE; docs/estimator.md)."""
    max_landmark_factors: int | None = None
    """Most bearing factors on live landmarks added per frame; None = one per observation.
    Beyond it, the observed landmarks whose last factor is oldest get one (ties spread
    over the bearings); the others still count as observed. A camera sees ~100 live
    landmarks a frame, and each factor makes iSAM2 re-eliminate that landmark with all
    its earlier factors: the update's cost grows with factors per frame x per landmark."""
    max_innovation_rad: float | None = math.radians(90.0)
    """Innovation gate (see BearingSlam._gate; None: off): an observation of a landmark
    at least gate_min_age_frames old whose bearing lies more than this from the one
    predicted at the odometry's pose, in a frame where another observation lies within
    gate_confirm_rad of its prediction, gets no factor. MRCLAM-6 has 9 observations in
    17 383 that are 150-172 deg off the truth (robot 3 sees landmark 20 behind it for
    four frames, robot 5 sees 20 once and 18 for four frames): a robust loss cannot
    shrug off four in a row, and replayed from frame 500 robot 3's map flipped by 171
    deg on them."""
    gate_min_age_frames: int = 100
    """The innovation gate applies to landmarks at least this many frames old (a young
    landmark's estimate may still be far off)."""
    gate_confirm_rad: float = math.radians(20.0)
    """The innovation gate applies only in a frame where another observation lies within
    this of its prediction (which confirms the odometry's pose)."""
    keyframe_for_candidate_rays: bool = False
    """A pose leaving the window stays as a keyframe while it holds the first ray of a
    candidate track, so that the candidate, once it triangulates, still has its widest
    baseline and links the poses it was first seen from. Off by default: on MRCLAM-6
    it fixes robot 3 (ATE 0.65 -> 0.18 m: early rays were lost with their poses and the
    landmarks initialised from a drifted chain stayed ~1 m off) and robot 1, but robot
    4 initialises a landmark 3 m off from rays 130 frames apart and gets worse (0.45 ->
    1.44 m); see bench.window_study."""
    drop_window_observations: bool = False
    """A pose that leaves the window without becoming a keyframe loses its landmark
    observations instead of having them marginalised: only its odometry is folded into
    the next pose, so no dense marginal over every landmark it saw builds up (keyframes
    keep theirs). Information is thrown away: less accurate, much cheaper with many
    landmarks per frame."""
    allow_new_landmarks: bool = True
    """False freezes the map (localisation mode): no candidates become landmarks."""
    window_observations: int | None = 900
    """A window of sparse observations grows beyond pose_window, up to max_pose_window
    poses, while its poses hold fewer bearing factors than this (what an update costs);
    a pose beyond pose_window leaves early, two in a frame, once they hold 5 % more.
    None: a capped map keeps pose_window's poses, an uncapped one grows by
    uncapped_window_observations (see window_factor_bound). Capped maps grow too by
    default: at cap 8 on MRCLAM-6 robot 1 (policy information) the 100-pose window
    alone gave ATE 0.403 m (0.289 aligned), the grown one 0.164 (0.142), every pose
    kept 0.183 (0.145), the batch over every observation 0.143 (0.135); a frame cost
    ~1.6x. A map with many bearings a frame (the lifelong world, ~10; cameras, ~50)
    keeps pose_window's 100 poses anyway."""
    uncapped_window_observations: int | None = 900
    """window_observations of a map without a landmark cap, when window_observations is
    None; None = pose_window alone. At 900 on MRCLAM-6 (~1.7 bearings a frame) the
    window keeps ~500 poses and the uncapped bounded graph matches the one that keeps
    every pose (ATE 0.280 m against 0.550 with 100 poses and 0.279 with every pose); the
    lifelong sim (~10 a frame) and camera maps (~50) keep pose_window's 100 anyway.
    (Used only where window_observations is None: maps stored before capped maps grew.)"""
    max_pose_window: int = 600
    """Most poses of a grown window (see window_factor_bound; pose_window if that is more)."""
    window_marginals: int | None = 128
    """A window grows beyond pose_window only while fewer than this many marginal
    factors touch its poses, and sheds a pose a frame while more than this (+ 5 %) do;
    None: no such bound. Each removed landmark leaves a dense marginal on the poses that
    saw it, evaluated in Python at every iSAM2 dogleg step: on the dense lifelong world
    (~25 bearings a frame, ~2 removals a frame, but few of the bearings on live
    landmarks, so window_observations let the window grow to 470 poses) 1 111 of them
    made a frame cost 226 ms (median over 1 000 frames) and p99 6.3x that; the window
    of pose_window poses, 57 ms and 2.6x. MRCLAM-6 never reaches it: at most 80 at cap
    8, 1 uncapped."""
    removal_margin: int = 0
    """When the live count exceeds landmark_cap, the policy removes landmarks down to
    landmark_cap - removal_margin, in one marginalisation. A removal costs one iSAM2
    update however many landmarks it takes, so a margin lets a map that meets new
    landmarks every frame (a camera map) pay for one every few frames. 0: down to the
    cap, one frame at a time as it is exceeded."""
    spare_observed: bool = False
    """The policy chooses among the live landmarks the frame did not observe (all of
    them only if it must remove more than those). A landmark removed while in view comes
    back within a second at ~25 bearings a frame (its archive entry's restore_min_rays
    are met at once) and is removed again: on the dense lifelong world, 1 646 removals
    in 1 000 frames, 1 548 of them restored, against 166 and 69 with this rule. Off by
    default: at cap 8 on MRCLAM-6 (~1.7 bearings a frame) it made the coverage policy's
    mean ATE 0.415 m against 0.305, worse on every robot (docs/measurements/lifelong.md): there,
    removing the newest, least-known landmark is what keeps the established ones."""

    graph_frame_distance_m: float | None = None
    """Off (None) by default: every frame enters the graph. Set, a frame enters the graph
    only when its robot moved this far since its last frame that did, turned
    graph_frame_angle_rad, graph_frame_max_gap frames went by, the frame sees fewer than
    graph_frame_min_landmarks live landmarks, or it starts or re-anchors the robot's
    chain. The other frames are tracked (see BearingSlam._track): their pose is solved
    against the graph's landmarks held fixed, kept relative to the robot's last graph
    frame, and their odometry is folded into the next graph frame's. A camera sees the
    same ~100 landmarks from nearly the same place frame after frame; in the graph, each
    such frame makes iSAM2 re-eliminate them all and links one more pose into every
    removed landmark's dense marginal."""
    graph_frame_angle_rad: float = math.radians(45.0)
    """With graph_frame_distance_m: a frame that turned this far from its robot's last
    graph frame enters the graph."""
    graph_frame_max_gap: int = 8
    """Most frames of a robot between two of its graph frames (tracked ones in between)."""
    graph_frame_min_landmarks: int = 5
    """A frame seeing fewer live landmarks than this enters the graph (tracking needs them)."""

    @property
    def window_factor_bound(self) -> int | None:
        """The bearing factors below which the window grows beyond pose_window (None:
        it does not): window_observations if given, else uncapped_window_observations
        for a map without a landmark cap."""
        if self.window_observations is not None or self.landmark_cap is not None:
            return self.window_observations
        return self.uncapped_window_observations

    def __post_init__(self) -> None:
        if self.landmark_cap is not None and self.landmark_cap < 1:
            raise ValueError("landmark_cap must be >= 1 or None")
        if self.removal_margin < 0 or (
            self.landmark_cap is not None and self.removal_margin >= self.landmark_cap
        ):
            raise ValueError("removal_margin must be >= 0 and below landmark_cap")
        if self.window_marginals is not None and self.window_marginals < 1:
            raise ValueError("window_marginals must be >= 1 or None")
        if self.pose_window is not None and self.pose_window < 2:
            raise ValueError("pose_window must be >= 2 or None")
        if not (self.bearing_sigma_rad > 0 and math.isfinite(self.bearing_sigma_rad)):
            raise ValueError("bearing_sigma_rad must be a positive finite number")
        if self.huber_k is not None and not self.huber_k > 0:
            raise ValueError("huber_k must be > 0 or None")
        if self.min_rays < 2 or self.max_rays < self.min_rays:
            raise ValueError("need 2 <= min_rays <= max_rays")
        if not 0 <= self.candidate_first_rays < self.max_rays:
            raise ValueError("need 0 <= candidate_first_rays < max_rays")
        if not 0 <= self.min_depth_m < self.max_depth_m:
            raise ValueError("need 0 <= min_depth_m < max_depth_m")
        if self.bearing_loss not in ("huber", "geman_mcclure"):
            raise ValueError("bearing_loss must be 'huber' or 'geman_mcclure'")
        if self.optimizer not in ("dogleg", "gauss_newton"):
            raise ValueError("optimizer must be 'dogleg' or 'gauss_newton'")
        if self.max_keyframes < 0:
            raise ValueError("max_keyframes must be >= 0")
        if self.max_linked_keyframes < 1:
            raise ValueError("max_linked_keyframes must be >= 1")
        if self.keyframe_placement not in ("spacing", "area"):
            raise ValueError("keyframe_placement must be 'spacing' or 'area'")
        if self.marginal_sparsification not in ("thin_keyframes", "chow_liu"):
            raise ValueError("marginal_sparsification must be 'thin_keyframes' or 'chow_liu'")
        if self.max_landmark_factors is not None and self.max_landmark_factors < 1:
            raise ValueError("max_landmark_factors must be >= 1 or None")
        if self.window_observations is not None and self.window_observations < 1:
            raise ValueError("window_observations must be >= 1 or None")
        if self.uncapped_window_observations is not None and self.uncapped_window_observations < 1:
            raise ValueError("uncapped_window_observations must be >= 1 or None")
        if self.graph_frame_distance_m is not None and not self.graph_frame_distance_m > 0:
            raise ValueError("graph_frame_distance_m must be > 0 or None")
        if not self.graph_frame_angle_rad > 0:
            raise ValueError("graph_frame_angle_rad must be > 0")
        if self.graph_frame_max_gap < 1:
            raise ValueError("graph_frame_max_gap must be >= 1")
        if self.graph_frame_min_landmarks < 0:
            raise ValueError("graph_frame_min_landmarks must be >= 0")
        if self.max_pose_window < 2:
            raise ValueError("max_pose_window must be >= 2")
        if self.candidate_ttl_frames < 1:
            raise ValueError("candidate_ttl_frames must be >= 1")
        if self.restore_after_frames < 0 or self.restore_min_rays < 1:
            raise ValueError("need restore_after_frames >= 0 and restore_min_rays >= 1")
        if not (self.restore_prior_sigma_m > 0 and math.isfinite(self.restore_prior_sigma_m)):
            raise ValueError("restore_prior_sigma_m must be a positive finite number")
        self._check_thresholds()

    def _check_thresholds(self) -> None:
        """Refuse thresholds that would silently switch a stage off or make no sense."""
        positive = {
            "min_parallax_rad": self.min_parallax_rad,
            "max_residual_sigmas": self.max_residual_sigmas,
            "max_position_sigma_m": self.max_position_sigma_m,
            "keyframe_angle_rad": self.keyframe_angle_rad,
            "gate_confirm_rad": self.gate_confirm_rad,
        }
        for name, value in positive.items():
            if not value > 0:
                raise ValueError(f"{name} must be > 0")
        for name, optional in (
            ("landmark_prior_sigma_m", self.landmark_prior_sigma_m),
            ("max_innovation_rad", self.max_innovation_rad),
        ):
            if optional is not None and not (optional > 0 and math.isfinite(optional)):
                raise ValueError(f"{name} must be a positive finite number or None")
        if self.upkeep not in get_args(Upkeep):
            raise ValueError(f"upkeep must be one of {get_args(Upkeep)}")
        if self.relinearize_threshold < 0 or self.relinearize_skip < 1:
            raise ValueError("need relinearize_threshold >= 0 and relinearize_skip >= 1")
        if self.relinearise_budget is not None and self.relinearise_budget < 1:
            raise ValueError("relinearise_budget must be >= 1 or None")
        if self.keyframe_distance_m < 0 or self.gate_min_age_frames < 0:
            raise ValueError("keyframe_distance_m and gate_min_age_frames must be >= 0")
        sigmas = (
            *self.odometry_sigma_floor,
            *self.odometry_sigma_per_metre,
            *self.odometry_sigma_per_sqrt_metre,
            *self.odometry_sigma_per_sqrt_second,
            *self.initial_pose_sigma,
            self.odometry_sigma_per_radian,
            self.odometry_sigma_per_sqrt_radian,
        )
        if not all(s >= 0 and math.isfinite(s) for s in sigmas):
            raise ValueError("odometry and initial-pose sigmas must be finite and >= 0")
