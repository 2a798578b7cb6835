"""Every frame's pose, with what is held in memory bounded by what can still move.

A frame's trajectory row is *held* while its pose can still change: its pose is in
the graph (a window pose or a keyframe), or the row is stored relative to a pose that
is (a tracked frame; a window pose that left without becoming a keyframe and follows
the robot's last keyframe). Once the pose a row follows is marginalised, the row is
*final*: its absolute pose never changes again.

Held rows are bounded by the graph (its poses and the frames anchored to them), not
by the robot's lifetime. Final rows are either kept here in compact arrays (`keep`:
a replay that wants every pose at the end) or handed to a sink by the estimator and
forgotten (a lifelong map: the service writes them to its store), so that the
estimator's memory and its snapshots do not grow with the frames.
"""

from __future__ import annotations

from array import array
from collections.abc import Iterable
from dataclasses import dataclass, field

import gtsam
import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True, slots=True)
class PoseRow:
    """One final trajectory row: a frame's pose in the map frame (m, rad)."""

    frame: int
    """The estimator's frame index (0-based, in processing order over all robots)."""
    robot: str
    seq: int
    stamp: float
    x: float
    y: float
    theta: float


FinalRow = tuple[int, int, int, float, float, float, float]
"""(frame, robot slot, seq, stamp, x, y, theta): a row as `Trajectory.finalise` releases it."""


def pose_rows(rows: Iterable[FinalRow], robots: list[str]) -> list[PoseRow]:
    """Released rows as a sink receives them; `robots` names the slots."""
    return [
        PoseRow(frame, robots[slot], seq, stamp, x, y, theta)
        for frame, slot, seq, stamp, x, y, theta in rows
    ]


def with_final_rows(
    final: NDArray[np.float64] | None, held: NDArray[np.float64] | None
) -> NDArray[np.float64]:
    """One robot's rows by seq, (N, 5) seq, stamp, x, y, theta as BearingSlam.trajectory
    gives them: the rows the estimator holds, and the final rows (from a sink or the
    store) of every other seq. The held rows need not follow the final ones (a keyframe
    stays held while the frames after it are made final), and a held row may carry a seq
    the store has made final since (a published view's rows): the held one is kept."""
    if held is None or not len(held):
        return final if final is not None and len(final) else np.zeros((0, 5))
    if final is None or not len(final):
        return held
    rows = np.concatenate([final[~np.isin(final[:, 0], held[:, 0])], held])
    return rows[np.argsort(rows[:, 0], kind="stable")]


@dataclass(frozen=True, slots=True)
class TrajectoryRows:
    """Rows sorted by frame index: `frame` (N,), `slot` (N,) the robot's slot, `seq`
    (N,), `stamp` (N,), `pose` (N, 3) x, y, theta (absolute, or relative for a row
    that follows a pose in the graph: the caller resolves those)."""

    frame: NDArray[np.int64]
    slot: NDArray[np.int32]
    seq: NDArray[np.int64]
    stamp: NDArray[np.float64]
    pose: NDArray[np.float64]

    def index(self, frames: NDArray[np.int64]) -> NDArray[np.intp]:
        """Row positions of `frames` (each must be present)."""
        return np.searchsorted(self.frame, frames)


@dataclass(slots=True)
class Trajectory:
    """Held rows by frame index, plus the final rows kept (see the module docstring)."""

    _held: dict[int, tuple[int, int, float, float, float, float]] = field(default_factory=dict)
    """frame -> (slot, seq, stamp, x, y, theta)."""
    _frame: array[int] = field(default_factory=lambda: array("q"))
    _slot: array[int] = field(default_factory=lambda: array("i"))
    _seq: array[int] = field(default_factory=lambda: array("q"))
    _stamp: array[float] = field(default_factory=lambda: array("d"))
    _pose: array[float] = field(default_factory=lambda: array("d"))
    """The kept final rows, in the order they became final (x, y, theta each)."""

    @property
    def held_count(self) -> int:
        return len(self._held)

    @property
    def kept_count(self) -> int:
        return len(self._frame)

    def append(self, frame: int, slot: int, seq: int, stamp: float, pose: gtsam.Pose2) -> None:
        """A new frame's row, held."""
        self._held[frame] = (slot, seq, stamp, pose.x(), pose.y(), pose.theta())

    def pose_at(self, frame: int) -> gtsam.Pose2:
        """A held row's pose (KeyError once the row is final)."""
        row = self._held[frame]
        return gtsam.Pose2(row[3], row[4], row[5])

    def set_pose(self, frame: int, pose: gtsam.Pose2) -> None:
        slot, seq, stamp = self._held[frame][:3]
        self._held[frame] = (slot, seq, stamp, pose.x(), pose.y(), pose.theta())

    def finalise(self, frames: Iterable[int]) -> list[FinalRow]:
        """Release held rows whose pose will not change again."""
        return [(frame, *self._held.pop(frame)) for frame in frames]

    def keep(self, rows: Iterable[FinalRow]) -> None:
        """Keep final rows here (an estimator without a sink)."""
        for frame, slot, seq, stamp, x, y, theta in rows:
            self._frame.append(frame)
            self._slot.append(slot)
            self._seq.append(seq)
            self._stamp.append(stamp)
            self._pose.extend((x, y, theta))

    def rows(self) -> TrajectoryRows:
        """Kept and held rows, sorted by frame index (copies)."""
        held = self._held
        frame = np.concatenate(
            [np.frombuffer(self._frame, dtype=np.int64), np.fromiter(held, np.int64, len(held))]
        )
        values = np.array(list(held.values()), dtype=np.float64).reshape(-1, 6)
        slot = np.concatenate(
            [np.frombuffer(self._slot, dtype=np.int32), values[:, 0].astype(np.int32)]
        )
        seq = np.concatenate(
            [np.frombuffer(self._seq, dtype=np.int64), values[:, 1].astype(np.int64)]
        )
        stamp = np.concatenate([np.frombuffer(self._stamp, dtype=np.float64), values[:, 2]])
        pose = np.concatenate(
            [np.frombuffer(self._pose, dtype=np.float64).reshape(-1, 3), values[:, 3:6]]
        )
        order = np.argsort(frame, kind="stable")
        return TrajectoryRows(frame[order], slot[order], seq[order], stamp[order], pose[order])
