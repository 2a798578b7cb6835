"""The one place where angles are wrapped.

Convention: every angle in covslam is in radians and wrapped to the half-open
interval (-pi, pi]; +pi is kept, -pi maps to +pi.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

TWO_PI = 2.0 * math.pi


def wrap_angle(angle_rad: float) -> float:
    """Wrap one angle to (-pi, pi]."""
    return math.pi - (math.pi - angle_rad) % TWO_PI


def wrap_angles(angles_rad: ArrayLike) -> NDArray[np.float64]:
    """Wrap an array of angles (any shape) to (-pi, pi]."""
    a = np.asarray(angles_rad, dtype=np.float64)
    return np.pi - np.mod(np.pi - a, TWO_PI)


def angle_diff(a_rad: float, b_rad: float) -> float:
    """The signed difference a - b, wrapped to (-pi, pi]."""
    return wrap_angle(a_rad - b_rad)
