"""A pose covariance between the robot frame and the map frame.

Convention: a (3, 3) covariance of (x, y, theta); "robot frame" has x, y along the
robot's axes (as the estimator reports a pose's marginal), "map frame" along the
map's (as the particle filter and the front end's prediction use it).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def _rotation(theta: float) -> FloatArray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def to_map_frame(cov_robot: FloatArray, theta: float) -> FloatArray:
    """(3, 3) covariance of (x, y, theta) in the robot frame -> in the map frame."""
    r = _rotation(theta)
    return np.asarray(r @ np.asarray(cov_robot) @ r.T)


def to_robot_frame(cov_map: FloatArray, theta: float) -> FloatArray:
    """(3, 3) covariance of (x, y, theta) in the map frame -> in the robot frame."""
    r = _rotation(theta)
    return np.asarray(r.T @ np.asarray(cov_map) @ r)
