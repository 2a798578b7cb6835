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

Pure: GTSAM and numpy only.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray

from graph.angles import wrap_angle, wrap_angles
from graph.particles import FilterConfig, motion_sigmas, predicted_bearings

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
    xk, lk = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.L
    fixed = gtsam.noiseModel.Isotropic.Sigma(2, 1e-4)  # the map's landmarks are held
    landmark_keys: dict[tuple[float, float], int] = {}

    def _landmark(xy: FloatArray) -> int:
        key = (float(xy[0]), float(xy[1]))
        if key not in landmark_keys:
            j = landmark_keys[key] = len(landmark_keys)
            point = np.array(key)
            graph.add(gtsam.PriorFactorPoint2(lk(j), point, fixed))
            values.insert(lk(j), point)
        return landmark_keys[key]

    # Initial values: the estimate at the last frame, odometry composed backwards.
    poses = [gtsam.Pose2(*est)]
    for f in reversed(frames[1:]):
        odo = np.zeros(3) if f.odometry is None else f.odometry
        poses.append(poses[-1].compose(gtsam.Pose2(*odo).inverse()))
    poses.reverse()
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k, start in enumerate(poses):
        values.insert(xk(k), start)
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(cfg.prior_sigma, dtype=np.float64))
    graph.add(gtsam.PriorFactorPose2(xk(0), poses[0], prior))
    for k, f in enumerate(frames):
        if k > 0:
            odo = np.zeros(3) if f.odometry is None else np.asarray(f.odometry, np.float64)
            sig = motion_sigmas(odo, f.dt_s, filter_config)
            if f.odometry is None:
                sig = np.maximum(sig, (1.0, 1.0, math.pi))  # no odometry: nearly free
            noise = gtsam.noiseModel.Diagonal.Sigmas(sig)
            graph.add(gtsam.BetweenFactorPose2(xk(k - 1), xk(k), gtsam.Pose2(*odo), noise))
        for xy, z, s in zip(f.landmarks_xy, f.bearings_rad, f.sigmas_rad, strict=True):
            robust = gtsam.noiseModel.Robust.Create(
                gtsam.noiseModel.mEstimator.Huber.Create(1.345),
                gtsam.noiseModel.Isotropic.Sigma(1, float(s)),
            )
            graph.add(gtsam.BearingFactor2D(xk(k), lk(_landmark(xy)), gtsam.Rot2(float(z)), robust))
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
