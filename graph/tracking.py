"""Tracked frames: a pose solved against fixed landmarks, and odometry composed between
graph frames (see SlamConfig.graph_frame_distance_m and BearingSlam._track).

Convention: a pose's perturbation and covariance are in its own frame, as GTSAM's
``Pose2`` (x, y, theta): ``p (+) d = p.retract(d)``. Composing ``a (+) b`` moves a's
perturbation by ``Ad(b^-1)``, so the covariance of a chain of odometry steps is
``Ad(b^-1) S_a Ad(b^-1)^T + S_b``, which is what a BetweenFactorPose2 over the whole
chain takes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray

from graph.angles import wrap_angles

FloatArray = NDArray[np.float64]

_ITERATIONS = 8
_STEP_TOL = 1e-9
_EPS = 1e-6


@dataclass(frozen=True, slots=True)
class Motion:
    """Odometry composed since a robot's last graph frame: (x, y, theta) of the current
    frame in that frame's robot frame, its (3, 3) covariance in the current frame, and
    how many frames' odometry it holds."""

    xyt: tuple[float, float, float]
    covariance: FloatArray
    frames: int

    @property
    def pose(self) -> gtsam.Pose2:
        return gtsam.Pose2(*self.xyt)


def compose_motion(
    motion: Motion | None, step: tuple[float, float, float], step_sigmas: FloatArray
) -> Motion:
    """`motion` followed by one odometry step with diagonal one-sigma noise."""
    step_cov = np.diag(np.square(np.asarray(step_sigmas, dtype=np.float64)))
    if motion is None:
        return Motion((float(step[0]), float(step[1]), float(step[2])), step_cov, 1)
    b = gtsam.Pose2(*step)
    ad = np.asarray(b.inverse().AdjointMap())
    pose = motion.pose.compose(b)
    cov = ad @ motion.covariance @ ad.T + step_cov
    return Motion((pose.x(), pose.y(), pose.theta()), 0.5 * (cov + cov.T), motion.frames + 1)


@dataclass(frozen=True, slots=True)
class TrackedPose:
    """A tracked frame's pose and what its bearings said about it."""

    pose: gtsam.Pose2
    information: FloatArray
    """(3, 3) information of the bearings alone, in the pose's frame (Huber-weighted)."""
    covariance: FloatArray
    """(3, 3) covariance given the base pose: the motion's prior and the bearings."""


def bearing_jacobians(pose: gtsam.Pose2, xy: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Predicted bearings (L,) of landmarks `xy` (L, 2) from `pose`, and their (L, 3)
    derivatives with respect to the pose's own-frame perturbation (x, y, theta)."""
    c, s = math.cos(pose.theta()), math.sin(pose.theta())
    dx, dy = xy[:, 0] - pose.x(), xy[:, 1] - pose.y()
    r2 = np.maximum(dx * dx + dy * dy, 1e-12)
    predicted = np.arctan2(dy, dx) - pose.theta()
    # d(bearing)/d(world x, y) = (dy, -dx) / r^2; the own-frame step moves x, y by R d.
    jx, jy = dy / r2, -dx / r2
    jac = np.column_stack([jx * c + jy * s, -jx * s + jy * c, -np.ones(len(xy))])
    return predicted, jac


def _local_jacobian(origin: gtsam.Pose2, pose: gtsam.Pose2) -> FloatArray:
    """(3, 3) derivative of origin.localCoordinates(pose.retract(d)) at d = 0 (central
    differences; it is the identity up to the size of the prior's error)."""
    out = np.empty((3, 3))
    for i in range(3):
        d = np.zeros(3)
        d[i] = _EPS
        plus = np.asarray(origin.localCoordinates(pose.retract(d)))
        minus = np.asarray(origin.localCoordinates(pose.retract(-d)))
        out[:, i] = (plus - minus) / (2 * _EPS)
    return out


def solve_pose(
    base: gtsam.Pose2,
    motion: Motion,
    xy: FloatArray,
    bearings: FloatArray,
    sigmas: FloatArray,
    huber_k: float | None,
) -> TrackedPose:
    """The pose of a frame from its bearings to landmarks held fixed at `xy` and the
    prior `base (+) motion` (base held fixed too): Gauss-Newton on the pose's own-frame
    perturbation, with the bearing factors' Huber weights."""
    prior = base.compose(motion.pose)
    prior_info = np.linalg.inv(motion.covariance)
    pose = prior
    weights = np.ones(len(xy))
    info = np.zeros((3, 3))
    hessian = prior_info
    for _ in range(_ITERATIONS):
        predicted, jac = bearing_jacobians(pose, xy)
        resid = wrap_angles(bearings - predicted)
        whitened = np.abs(resid) / sigmas
        if huber_k is not None:
            weights = np.where(whitened <= huber_k, 1.0, huber_k / np.maximum(whitened, 1e-12))
        w = weights / np.square(sigmas)
        info = (jac * w[:, None]).T @ jac
        # The prior's error at the current pose and its derivative by the step.
        e0 = np.asarray(prior.localCoordinates(pose))
        d0 = _local_jacobian(prior, pose)
        hessian = d0.T @ prior_info @ d0 + info
        gradient = (jac * w[:, None]).T @ resid - d0.T @ prior_info @ e0
        step = np.linalg.solve(hessian, gradient)
        pose = pose.retract(step)
        if float(np.max(np.abs(step))) < _STEP_TOL:
            break
    covariance = np.linalg.inv(hessian)
    return TrackedPose(pose, info, 0.5 * (covariance + covariance.T))


def tracked_covariance(
    base_covariance: FloatArray, motion: Motion, information: FloatArray
) -> FloatArray:
    """(3, 3) covariance of a tracked pose with its base pose's uncertainty: the base's
    covariance carried along the motion, plus the motion's, updated by the bearings."""
    ad = np.asarray(motion.pose.inverse().AdjointMap())
    prior = ad @ np.asarray(base_covariance, dtype=np.float64) @ ad.T + motion.covariance
    cov = np.linalg.inv(np.linalg.inv(prior) + information)
    return 0.5 * (cov + cov.T)
