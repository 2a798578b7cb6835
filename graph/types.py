"""Plain inputs and outputs of the estimation core.

Conventions (DESIGN.md): SI units; map frame x, y, yaw theta counter-clockwise
from +x (REP-103). A bearing is measured in the robot frame, counter-clockwise
from the robot's forward axis (+x), wrapped to (-pi, pi]. Odometry is the motion
since the robot's previous frame expressed in the previous robot frame.
"""

from __future__ import annotations

from dataclasses import MISSING, dataclass, field, fields
from typing import Any


@dataclass(frozen=True, slots=True)
class Pose2D:
    """A planar pose in the map frame: metres, metres, radians (CCW from +x)."""

    x: float
    y: float
    theta: float


@dataclass(frozen=True, slots=True)
class Odometry:
    """Motion since the previous frame, in the previous robot frame.

    dx, dy in metres, dtheta in radians. Optional one-sigma noise per axis; when
    absent the map's odometry noise model (growing with the motion) is used.
    """

    dx: float
    dy: float
    dtheta: float
    sigma_x: float | None = None
    sigma_y: float | None = None
    sigma_theta: float | None = None


@dataclass(frozen=True, slots=True)
class BearingObservation:
    """One bearing to a landmark, radians in the robot frame, CCW from +x.

    `label` is the known data association (e.g. a fiducial id). `sigma_rad` is
    the one-sigma bearing noise; None means the map's default.
    """

    bearing_rad: float
    label: str
    sigma_rad: float | None = None


@dataclass(frozen=True, slots=True)
class FrameInput:
    """One frame of one robot, as the REST frame format describes it."""

    robot: str
    seq: int
    stamp: float
    odometry: Odometry | None = None
    initial_pose: Pose2D | None = None
    observations: tuple[BearingObservation, ...] = field(default_factory=tuple)


def restore_fields(obj: Any, state: list[Any] | tuple[Any, ...]) -> None:
    """Set a frozen, slotted dataclass's fields from its pickled state (the values of
    its fields, in order): the body of its ``__setstate__``. A state pickled before
    later fields existed is shorter; those take their default (or their default
    factory's value). New fields therefore go last."""
    for f, value in zip(fields(obj), state, strict=False):
        object.__setattr__(obj, f.name, value)
    for f in fields(obj)[len(state) :]:
        default = f.default_factory() if f.default is MISSING else f.default  # type: ignore[operator]
        object.__setattr__(obj, f.name, default)
