"""Checks a frame before anything in the map changes; raises InvalidFrame."""

from __future__ import annotations

import math

from graph.errors import InvalidFrame, OutOfOrderFrame, UnknownRobot
from graph.types import FrameInput


def _finite(value: object, field: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InvalidFrame(field, f"must be a number, got {type(value).__name__}")
    if not math.isfinite(value):
        raise InvalidFrame(field, f"must be finite, got {value!r}")
    return float(value)


def _positive(value: object, field: str) -> None:
    if _finite(value, field) <= 0.0:
        raise InvalidFrame(field, f"must be > 0, got {value!r}")


def validate_frame(
    frame: FrameInput,
    *,
    last_seq: int | None,
    last_stamp: float | None,
    require_initial_pose: bool = True,
) -> None:
    """Refuse a frame that the map cannot take, naming the field and the reason.

    `last_seq`/`last_stamp` describe the robot's last accepted frame (None for a
    robot the map has not seen). With `require_initial_pose` False a new robot may
    come without one (the place localiser will find it).
    """
    if not isinstance(frame.robot, str) or not frame.robot:
        raise InvalidFrame("robot", "must be a non-empty string")
    if isinstance(frame.seq, bool) or not isinstance(frame.seq, int) or frame.seq < 0:
        raise InvalidFrame("seq", f"must be an integer >= 0, got {frame.seq!r}")
    stamp = _finite(frame.stamp, "stamp")
    if last_seq is not None and frame.seq <= last_seq:
        raise OutOfOrderFrame(
            "seq", f"{frame.seq} is not after robot {frame.robot!r}'s last seq {last_seq}"
        )
    if last_stamp is not None and stamp < last_stamp:
        raise OutOfOrderFrame(
            "stamp", f"{stamp} s is before robot {frame.robot!r}'s last stamp {last_stamp} s"
        )
    if last_seq is None:
        if frame.initial_pose is None and require_initial_pose:
            raise UnknownRobot(
                "initial_pose",
                f"robot {frame.robot!r} is new to this map and its frame has no initial_pose",
            )
        if frame.initial_pose is not None:
            for name in ("x", "y", "theta"):
                _finite(getattr(frame.initial_pose, name), f"initial_pose.{name}")
    else:
        odo = frame.odometry
        if odo is None:
            raise InvalidFrame("odometry", "is required on every frame after a robot's first")
        for name in ("dx", "dy", "dtheta"):
            _finite(getattr(odo, name), f"odometry.{name}")
        if abs(odo.dtheta) > math.pi:
            raise InvalidFrame("odometry.dtheta", f"must lie in [-pi, pi], got {odo.dtheta!r}")
        for name in ("sigma_x", "sigma_y", "sigma_theta"):
            if getattr(odo, name) is not None:
                _positive(getattr(odo, name), f"odometry.{name}")
    seen: dict[str, int] = {}
    for i, obs in enumerate(frame.observations):
        where = f"observations[{i}]"
        bearing = _finite(obs.bearing_rad, f"{where}.bearing")
        if not -math.pi < bearing <= math.pi:
            raise InvalidFrame(f"{where}.bearing", f"must lie in (-pi, pi] rad, got {bearing!r}")
        if obs.sigma_rad is not None:
            _positive(obs.sigma_rad, f"{where}.sigma")
        if not isinstance(obs.label, str) or not obs.label:
            raise InvalidFrame(f"{where}.label", "must be a non-empty string")
        if obs.label in seen:
            raise InvalidFrame(
                f"{where}.label",
                f"landmark {obs.label!r} is observed twice in one frame "
                f"(also observations[{seen[obs.label]}])",
            )
        seen[obs.label] = i
