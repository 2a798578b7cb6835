"""A converged filter's pose checked against the robot's recent frames (labelled maps).

A particle filter can collapse onto a pose its recent bearings only partly determine
(sample impoverishment after a sharp update) or onto one that fits the latest few frames
by chance. Before a robot is relocalised at the filter's estimate, the frames of its
search (odometry and labelled bearings to the map's landmarks, held fixed) are solved
again as a small pose graph started at the estimate (earlier poses by composing the
odometry backwards), with a broad prior on the first pose:

- ``refuted``: the solved poses leave too many bearings beyond ``outlier_sigmas`` (the
  estimate explains the frames only by chance), or the solved latest pose lies beyond
  the gate from the filter's estimate;
- ``wait``: the frames do not yet determine the latest pose as tightly as the filter's
  convergence test asks (its Cramer-Rao bound at the solution is wider): the filter is
  surer than its data allow;
- ``confirmed`` otherwise.

The same small pose graph tests a tracked robot's old pose (`rejects_old_pose`): do the
frames since the graph's pose stopped explaining them reject the pose just before them?
(The localiser's kidnap test; see docs/localisation.md.)

Pure: GTSAM and numpy only.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from graph.angles import wrap_angle, wrap_angles
from graph.particles import FilterConfig, motion_sigmas, predicted_bearings
from graph.types import restore_fields

FloatArray = NDArray[np.float64]

CONFIRMED = "confirmed"
WAIT = "wait"
REFUTED = "refuted"


@dataclass(frozen=True, slots=True)
class WindowFrame:
    """One frame of a robot's search: its odometry from the previous frame (None on the
    first), the seconds since it, and its labelled bearings to mapped landmarks."""

    odometry: FloatArray | None
    dt_s: float
    landmarks_xy: FloatArray
    """(M, 2) map positions of the observed landmarks."""
    bearings_rad: FloatArray
    sigmas_rad: FloatArray
    """(M,) the sensor model's sigma of each bearing."""
    labels: tuple[str, ...] = ()
    """(M,) the observed landmarks' labels (empty: a landmark is known by its position,
    which the graph moves between frames)."""

    def __setstate__(self, state: tuple[Any, ...]) -> None:
        restore_fields(self, state)  # also a state pickled before later fields existed


@dataclass(frozen=True, slots=True)
class WindowCheckConfig:
    prior_sigma: tuple[float, float, float] = (10.0, 10.0, math.pi)
    """The first frame's prior (no initial pose)."""
    outlier_sigmas: float = 3.0
    """A bearing whose residual at the solution exceeds this many sigmas misfits."""
    max_misfit_share: float = 0.2
    """Refuted when more than this share of the latest `misfit_frames` frames' bearings
    misfit."""
    misfit_frames: int = 30
    """The latest frames whose bearings are counted for misfits (older frames still
    shape the solution): a few landmarks the map got wrong where the robot was (e.g.
    from the frames the graph took between a kidnap and `lost`) keep misfitting in the
    frames that saw them, and the robot has moved on since."""
    gate: float = 16.27
    """Squared Mahalanobis distance (3 dof, 99.9 %) of the solved latest pose from the
    filter's estimate under the sum of their covariances, beyond which it is refuted."""
    information_slack: float = 2.0
    """The solved pose's sigmas may exceed the filter's convergence test by this factor.
    (MRCLAM-6, surveyed map, 4 x 50 starts: relocalised beyond 0.5 m / 15 deg 8 times
    without the check; 3 with refutation alone; 2 at 1.25 but a median up to 4 frames
    later, the 1 deg-floored sensor model being wider than the data's 0.3-0.6 deg; 2 at
    2.0 with the medians unchanged.)"""
    landmark_sigma_m: float = 0.0
    """Position sigma (m) of each of the map's landmarks in the check; 0: held where the
    map puts them. Above 0 the solved pose's covariance includes how far the map's own
    errors could move it, so the check waits longer where the robot has seen few
    landmarks: fewer wrong relocalisations on a map a few decimetres off in places, at
    the cost of frames (docs/measurements/localisation.md)."""
    stable_frames: int = 0
    """0: a confirmed check relocalises the robot at once. Above 0 the check's solution
    must also hold: confirmed again this many frames later, within stable_tolerance of
    the first solution moved on by the odometry since (else the wait starts again from
    the newer one). Where the map is locally a few decimetres off, the pose it implies
    still moves as the robot sees more of it: fewer wrong relocalisations, at the cost
    of frames (docs/measurements/localisation.md)."""
    stable_tolerance: tuple[float, float] = (0.1, math.radians(3.0))
    """Metres and radians the solution may move over stable_frames."""

    def __setstate__(self, state: tuple[Any, ...]) -> None:
        restore_fields(self, state)  # also a state pickled before later fields existed


@dataclass(frozen=True, slots=True)
class WindowVerdict:
    verdict: str
    pose_xytheta: FloatArray
    covariance: FloatArray
    misfit_share: float
    bearings: int


def check_window(
    estimate_xytheta: FloatArray,
    estimate_covariance: FloatArray,
    frames: Sequence[WindowFrame],
    filter_config: FilterConfig,
    config: WindowCheckConfig | None = None,
) -> WindowVerdict:
    """The verdict on the filter's estimate (pose (3,), covariance (3, 3)) of the last of
    `frames` (see the module docstring)."""
    cfg = config or WindowCheckConfig()
    est = np.asarray(estimate_xytheta, dtype=np.float64)
    n = len(frames)
    xk = gtsam.symbol_shorthand.X
    poses = _backwards(est, frames)
    graph, values = _window_graph(
        frames, poses, filter_config, loss=_huber, landmark_sigma_m=cfg.landmark_sigma_m
    )
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(cfg.prior_sigma, dtype=np.float64))
    graph.add(gtsam.PriorFactorPose2(xk(0), poses[0], prior))
    bearings = sum(len(f.bearings_rad) for f in frames)
    try:
        solved = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
        cov = gtsam.Marginals(graph, solved).marginalCovariance(xk(n - 1))
    except RuntimeError:  # an indeterminate system: the frames do not fix the pose
        return WindowVerdict(WAIT, est, np.diag(np.square(cfg.prior_sigma)), 0.0, bearings)
    misfits = counted = 0
    for k in range(max(n - cfg.misfit_frames, 0), n):
        f, p = frames[k], solved.atPose2(xk(k))
        counted += len(f.bearings_rad)
        if len(f.bearings_rad):
            predicted = predicted_bearings(np.array([[p.x(), p.y(), p.theta()]]), f.landmarks_xy)
            residual = wrap_angles(predicted[0] - np.asarray(f.bearings_rad, np.float64))
            misfits += int(np.count_nonzero(np.abs(residual) > cfg.outlier_sigmas * f.sigmas_rad))
    last = solved.atPose2(xk(n - 1))
    pose = np.array([last.x(), last.y(), last.theta()])
    share = misfits / counted if counted else 0.0
    e = pose - est
    e[2] = wrap_angle(float(e[2]))
    d2 = float(e @ np.linalg.solve(cov + np.asarray(estimate_covariance, np.float64), e))
    if share > cfg.max_misfit_share or d2 > cfg.gate:
        return WindowVerdict(REFUTED, pose, cov, share, bearings)
    sigma_xy = math.sqrt(max(float(np.linalg.eigvalsh(cov[:2, :2])[-1]), 0.0))
    sigma_theta = math.sqrt(max(float(cov[2, 2]), 0.0))
    slack = cfg.information_slack
    informed = (
        sigma_xy <= slack * filter_config.converged_sigma_m
        and sigma_theta <= slack * filter_config.converged_sigma_rad
    )
    return WindowVerdict(CONFIRMED if informed else WAIT, pose, cov, share, bearings)


def _backwards(last_xytheta: FloatArray, frames: Sequence[WindowFrame]) -> list[gtsam.Pose2]:
    """Poses of `frames` ending at `last_xytheta` (3,), earlier ones by composing the
    odometry backwards."""
    poses = [gtsam.Pose2(*np.asarray(last_xytheta, dtype=np.float64))]
    for f in reversed(frames[1:]):
        odo = np.zeros(3) if f.odometry is None else f.odometry
        poses.append(poses[-1].compose(gtsam.Pose2(*odo).inverse()))
    poses.reverse()
    return poses


def _huber() -> gtsam.noiseModel.mEstimator.Base:
    return gtsam.noiseModel.mEstimator.Huber.Create(1.345)


def _cauchy() -> gtsam.noiseModel.mEstimator.Base:
    """A loss that grows only logarithmically beyond one sigma, as the negative log of
    the filter's sensor model (a Gaussian and a uniform outlier floor) levels off: one
    wrong bearing (MRCLAM has a few, 30 deg off) costs about as much as a few sigmas."""
    return gtsam.noiseModel.mEstimator.Cauchy.Create(1.0)


def _window_graph(
    frames: Sequence[WindowFrame],
    poses: Sequence[gtsam.Pose2],
    filter_config: FilterConfig,
    *,
    loss: Callable[[], gtsam.noiseModel.mEstimator.Base],
    landmark_sigma_m: float = 0.0,
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """The frames as a pose graph over X(0..n-1) started at `poses`: odometry between
    consecutive frames (the filter's motion noise; nearly free without odometry) and
    each bearing to its landmark under the robust `loss`, the map's landmarks held
    (`landmark_sigma_m` 0) or each with a prior of that sigma at the map's position. No
    prior on any pose."""
    xk, lk = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.L
    fixed = gtsam.noiseModel.Isotropic.Sigma(2, max(landmark_sigma_m, 1e-4))
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    landmark_keys: dict[tuple[float, float], int] = {}

    def _landmark(xy: FloatArray) -> int:
        key = (float(xy[0]), float(xy[1]))
        if key not in landmark_keys:
            j = landmark_keys[key] = len(landmark_keys)
            point = np.array(key)
            graph.add(gtsam.PriorFactorPoint2(lk(j), point, fixed))
            values.insert(lk(j), point)
        return landmark_keys[key]

    for k, start in enumerate(poses):
        values.insert(xk(k), start)
    for k, f in enumerate(frames):
        if k > 0:
            odo = np.zeros(3) if f.odometry is None else np.asarray(f.odometry, np.float64)
            sig = motion_sigmas(odo, f.dt_s, filter_config)
            if f.odometry is None:
                sig = np.maximum(sig, (1.0, 1.0, math.pi))  # no odometry: nearly free
            noise = gtsam.noiseModel.Diagonal.Sigmas(sig)
            graph.add(gtsam.BetweenFactorPose2(xk(k - 1), xk(k), gtsam.Pose2(*odo), noise))
        for xy, z, s in zip(f.landmarks_xy, f.bearings_rad, f.sigmas_rad, strict=True):
            model = gtsam.noiseModel.Robust.Create(
                loss(), gtsam.noiseModel.Isotropic.Sigma(1, float(s))
            )
            graph.add(gtsam.BearingFactor2D(xk(k), lk(_landmark(xy)), gtsam.Rot2(float(z)), model))
    return graph, values


def old_pose_rejection(
    anchor_xytheta: FloatArray,
    anchor_covariance: FloatArray,
    frames: Sequence[WindowFrame],
    filter_config: FilterConfig,
    *,
    latest_xytheta: Sequence[FloatArray] = (),
) -> float:
    """How strongly `frames` reject the hypothesis that the robot was at the anchor pose
    ((3,), covariance (3, 3)) just before the first of them: the likelihood-ratio
    statistic ``2 (E(H0) - E(H1))`` of the frames' odometry and bearings (the map's
    landmarks held; bearings under a Cauchy loss, so that a few wrong ones cannot make
    it large) solved with the anchor as a prior on the first frame's pose moved by its
    odometry (H0) and with no prior at all (H1: anywhere). Under H0 it stays below
    chi^2 with 3 degrees of freedom (the loss is below the Gaussian's); each bearing H0
    cannot explain adds about ``log(1 + r^2)`` for a residual of r sigmas. H1 is solved
    from H0's solution and from each
    of `latest_xytheta` (the latest frame's pose; earlier ones by the odometry), and its
    best fit is taken (a local optimiser may miss a pose far from where it starts)."""
    xk = gtsam.symbol_shorthand.X
    anchor = gtsam.Pose2(*np.asarray(anchor_xytheta, dtype=np.float64))
    first = frames[0]
    odo0 = np.zeros(3) if first.odometry is None else np.asarray(first.odometry, np.float64)
    # The prior on the first frame: the anchor moved by the first frame's odometry, with
    # the anchor's covariance and that motion's noise (first-order, in the map frame).
    sig0 = motion_sigmas(odo0, first.dt_s, filter_config)
    if first.odometry is None:
        sig0 = np.maximum(sig0, (1.0, 1.0, math.pi))
    start = anchor.compose(gtsam.Pose2(*odo0))
    rot = np.eye(3)
    c, s = math.cos(anchor.theta()), math.sin(anchor.theta())
    rot[:2, :2] = [[c, -s], [s, c]]
    cov0 = np.asarray(anchor_covariance, np.float64) + rot @ np.diag(np.square(sig0)) @ rot.T
    rel = np.eye(3)
    c0, s0 = math.cos(start.theta()), math.sin(start.theta())
    rel[:2, :2] = [[c0, s0], [-s0, c0]]  # to the first pose's own frame (GTSAM's prior)
    h0_poses = [start]
    for f in frames[1:]:
        odo = np.zeros(3) if f.odometry is None else f.odometry
        h0_poses.append(h0_poses[-1].compose(gtsam.Pose2(*odo)))
    base, seed = _window_graph(frames, h0_poses, filter_config, loss=_cauchy)
    h0 = gtsam.NonlinearFactorGraph(base)
    h0.add(
        gtsam.PriorFactorPose2(
            xk(0), start, gtsam.noiseModel.Gaussian.Covariance(rel @ cov0 @ rel.T)
        )
    )
    try:
        fit0 = gtsam.LevenbergMarquardtOptimizer(h0, seed).optimize()
    except RuntimeError:
        return 0.0
    chi0 = 2.0 * h0.error(fit0)
    h1 = gtsam.NonlinearFactorGraph(base)
    loose = gtsam.noiseModel.Diagonal.Sigmas(np.array([100.0, 100.0, 10.0]))
    h1.add(gtsam.PriorFactorPose2(xk(0), start, loose))
    best = chi0
    starts = [fit0]
    for latest in latest_xytheta:
        values = gtsam.Values(seed)
        for k, pose in enumerate(_backwards(latest, frames)):
            values.update(xk(k), pose)
        starts.append(values)
    for values in starts:
        try:
            fit1 = gtsam.LevenbergMarquardtOptimizer(h1, values).optimize()
        except RuntimeError:
            continue
        best = min(best, 2.0 * h1.error(fit1))
    return chi0 - best


def rejects_old_pose(
    anchor_xytheta: FloatArray,
    anchor_covariance: FloatArray,
    frames: Sequence[WindowFrame],
    filter_config: FilterConfig,
    gate: float,
    *,
    latest_xytheta: Sequence[FloatArray] = (),
) -> tuple[bool, float]:
    """Whether `frames` reject the anchor pose (`old_pose_rejection` beyond `gate`) also
    without any one landmark's bearings, and the statistic (the least over the landmarks
    left out once it exceeds the gate). A single landmark's bearings do not make a
    kidnap: MRCLAM's robots misread a landmark's code for several frames in a row (robot
    5 took landmark 8, dead ahead, for 18 four frames running), and a landmark the map
    has wrong misfits from wherever it is seen."""
    stat = old_pose_rejection(
        anchor_xytheta, anchor_covariance, frames, filter_config, latest_xytheta=latest_xytheta
    )
    if stat <= gate:
        return False, stat
    for landmark in sorted({key for f in frames for key in _keys(f)}):
        rest = [_without(f, landmark) for f in frames]
        if not any(len(f.bearings_rad) for f in rest):
            return False, 0.0
        stat = min(
            stat,
            old_pose_rejection(
                anchor_xytheta,
                anchor_covariance,
                rest,
                filter_config,
                latest_xytheta=latest_xytheta,
            ),
        )
        if stat <= gate:
            return False, stat
    return True, stat


def _keys(frame: WindowFrame) -> list[str]:
    """Each bearing's landmark: its label, or its position when the frame has none."""
    if frame.labels:
        return list(frame.labels)
    return [f"{x!r},{y!r}" for x, y in frame.landmarks_xy]


def _without(frame: WindowFrame, landmark: str) -> WindowFrame:
    """`frame` without its bearings to `landmark` (see _keys)."""
    keep = np.array([key != landmark for key in _keys(frame)], dtype=bool)
    return WindowFrame(
        frame.odometry,
        frame.dt_s,
        frame.landmarks_xy[keep],
        frame.bearings_rad[keep],
        frame.sigmas_rad[keep],
        tuple(label for label, k in zip(frame.labels, keep, strict=False) if k),
    )
