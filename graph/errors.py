"""Typed errors of the estimation core. A raised InvalidFrame leaves the map unchanged."""

from __future__ import annotations


class InvalidFrame(ValueError):
    """A frame was refused before anything in the map changed.

    `field` names the offending field in the REST frame format (dotted path,
    e.g. ``observations[3].bearing``); `detail` says what was wrong.
    """

    def __init__(self, field: str, detail: str) -> None:
        super().__init__(f"{field}: {detail}")
        self.field = field
        self.detail = detail


class UnknownRobot(InvalidFrame):
    """A robot's first frame arrived without an initial pose."""


class OutOfOrderFrame(InvalidFrame):
    """A frame's seq is not greater than the robot's last accepted seq."""


class EstimationError(RuntimeError):
    """GTSAM refused an update (e.g. an indeterminate linear system)."""
