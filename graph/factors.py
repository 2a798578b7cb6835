"""Keys, noise models and the small functions that each build one kind of factor.

Keys (gtsam.symbol_shorthand): X for poses, L for landmarks. Each robot owns a
slot; its k-th pose is X(slot * POSES_PER_ROBOT + k), so one X chain per robot.
"""

from __future__ import annotations

import math
from functools import lru_cache

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X
from numpy.typing import NDArray

from graph.config import BearingLoss, SlamConfig
from graph.types import Odometry, Pose2D

POSES_PER_ROBOT = 1 << 40
LANDMARK_CHR = ord("l")


def pose_key(robot_slot: int, index: int) -> int:
    """The key of a robot's index-th pose."""
    return int(X(robot_slot * POSES_PER_ROBOT + index))


def landmark_key(landmark_id: int) -> int:
    """The key of a landmark (its stable API id)."""
    return int(L(landmark_id))


def is_landmark_key(key: int) -> bool:
    return gtsam.Symbol(key).chr() == LANDMARK_CHR


def landmark_key_mask(keys: NDArray[np.uint64]) -> NDArray[np.bool_]:
    """`is_landmark_key` of each of `keys` (a symbol's character is its top byte)."""
    return (keys >> np.uint64(56)) == np.uint64(LANDMARK_CHR)


def to_pose2(pose: Pose2D) -> gtsam.Pose2:
    return gtsam.Pose2(pose.x, pose.y, pose.theta)


def from_pose2(pose: gtsam.Pose2) -> Pose2D:
    return Pose2D(float(pose.x()), float(pose.y()), float(pose.theta()))


def odometry_sigmas(odometry: Odometry, config: SlamConfig, dt_s: float = 0.0) -> np.ndarray:
    """One-sigma noise (x m, y m, theta rad), shape (3,): given, or the map's model: a
    floor plus terms linear in the step's distance and turn, and in quadrature random
    walks in the distance, the turn and the time `dt_s` the step took (see SlamConfig)."""
    dist = math.hypot(odometry.dx, odometry.dy)
    floor = np.asarray(config.odometry_sigma_floor)
    per_m = np.asarray(config.odometry_sigma_per_metre)
    model = floor + per_m * dist
    model[2] += config.odometry_sigma_per_radian * abs(odometry.dtheta)
    variance = model**2 + np.square(config.odometry_sigma_per_sqrt_metre) * dist
    variance[2] += config.odometry_sigma_per_sqrt_radian**2 * abs(odometry.dtheta)
    if dt_s > 0:
        variance += np.square(config.odometry_sigma_per_sqrt_second) * dt_s
    model = np.sqrt(variance)
    given = (odometry.sigma_x, odometry.sigma_y, odometry.sigma_theta)
    return np.array([g if g is not None else m for g, m in zip(given, model, strict=True)])


def odometry_factor(
    previous: int, current: int, odometry: Odometry, config: SlamConfig, dt_s: float = 0.0
) -> gtsam.BetweenFactorPose2:
    noise = gtsam.noiseModel.Diagonal.Sigmas(odometry_sigmas(odometry, config, dt_s))
    motion = gtsam.Pose2(odometry.dx, odometry.dy, odometry.dtheta)
    return gtsam.BetweenFactorPose2(previous, current, motion, noise)


def pose_prior_factor(key: int, pose: Pose2D, config: SlamConfig) -> gtsam.PriorFactorPose2:
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(config.initial_pose_sigma))
    return gtsam.PriorFactorPose2(key, to_pose2(pose), noise)


BEARING_NOISE_MODELS = 256
"""Distinct bearing noise models kept for sharing (see `bearing_noise`): a map's
configured sigma takes one; front ends that give each feature its own sigma miss."""


@lru_cache(maxsize=BEARING_NOISE_MODELS)
def bearing_noise(
    sigma_rad: float, huber_k: float | None, loss: BearingLoss = "huber"
) -> gtsam.noiseModel.Base:
    """Isotropic noise of one bearing, robust with `loss` at `huber_k` sigmas (None:
    Gaussian).

    One model per distinct argument, shared by every factor built with it (the last
    BEARING_NOISE_MODELS kept): a GTSAM noise model is immutable, and a model of its own
    cost each bearing factor ~0.4 KiB of heap (the isotropic base, the robust kernel
    and their vectors), i.e. a few MiB of a lifelong map's resident memory when its
    window holds thousands of bearings."""
    base = gtsam.noiseModel.Isotropic.Sigma(1, sigma_rad)
    if huber_k is None:
        return base
    estimator = gtsam.noiseModel.mEstimator
    kernel = estimator.Huber if loss == "huber" else estimator.GemanMcClure
    return gtsam.noiseModel.Robust.Create(kernel.Create(huber_k), base)


def bearing_factor(
    pose: int,
    landmark: int,
    bearing_rad: float,
    sigma_rad: float,
    huber_k: float | None,
    loss: BearingLoss = "huber",
) -> gtsam.BearingFactor2D:
    return gtsam.BearingFactor2D(
        pose, landmark, gtsam.Rot2(bearing_rad), bearing_noise(sigma_rad, huber_k, loss)
    )


def landmark_prior_factor(
    key: int, position_xy: np.ndarray, sigma_m: float
) -> gtsam.PriorFactorPoint2:
    noise = gtsam.noiseModel.Isotropic.Sigma(2, sigma_m)
    return gtsam.PriorFactorPoint2(key, np.asarray(position_xy, dtype=float), noise)


VAGUE_LINK_SIGMAS = (100.0, 100.0, math.pi)
"""Sigmas (m, m, rad) of the link that keeps a re-anchored chain connected to its past."""


def vague_link(motion: gtsam.Pose2) -> Odometry:
    """An odometry measurement that says next to nothing (a gap the robot was carried
    over): it keeps the chain connected without pulling either side."""
    return Odometry(
        float(motion.x()),
        float(motion.y()),
        float(motion.theta()),
        *VAGUE_LINK_SIGMAS,
    )


def anchor_prior_factor(
    key: int, pose: Pose2D, covariance_map: np.ndarray, config: SlamConfig
) -> gtsam.PriorFactorPose2:
    """A prior from the place localiser: `covariance_map` is (3, 3) over the map-frame
    (x, y, theta); GTSAM wants it in the pose's own frame. Never tighter than the
    initial-pose prior."""
    c, s = math.cos(pose.theta), math.sin(pose.theta)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    local = rot.T @ np.asarray(covariance_map, dtype=np.float64) @ rot
    local = 0.5 * (local + local.T) + np.diag(np.square(config.initial_pose_sigma))
    return gtsam.PriorFactorPose2(key, to_pose2(pose), gtsam.noiseModel.Gaussian.Covariance(local))
