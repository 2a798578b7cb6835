"""Frames acknowledged while the graph does not take them (a robot initialising or lost).

Nothing acknowledged is ever lost: such a frame is kept with the best pose available
when it arrives -- the particle filter's estimate once the filter has converged, else
the pose dead-reckoned by the frame's odometry from the robot's last graph pose (for a
robot the graph never had: the filter's estimate, however vague). When the robot's
chain is anchored again, the frames of the gap are re-expressed relative to the anchor
frame by dead-reckoning *backwards* from it: the odometry after a kidnap is sound, the
pose before it is not. From then on they follow the graph's corrections of the anchor
frame's pose.

Poses are ``(x m, y m, theta rad)`` in the map frame; odometry is the motion since the
robot's previous frame in the previous robot frame (DESIGN.md, Conventions).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from graph.angles import wrap_angle

Pose = tuple[float, float, float]

ODOMETRY = "odometry"
"""Source of a pose dead-reckoned from a graph pose (forwards, or backwards after an anchor)."""
FILTER = "filter"
"""Source of a pose that is the particle filter's estimate."""


def compose(a: Pose, b: Pose) -> Pose:
    """``a`` followed by ``b`` (``b`` expressed in ``a``'s frame)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap_angle(a[2] + b[2]))


def inverse(a: Pose) -> Pose:
    c, s = math.cos(a[2]), math.sin(a[2])
    return (-c * a[0] - s * a[1], s * a[0] - c * a[1], wrap_angle(-a[2]))


@dataclass(frozen=True, slots=True)
class OffGraphFrame:
    seq: int
    stamp: float
    odometry: Pose | None
    """The frame's odometry (None on a robot's first frame)."""
    pose: Pose
    """Best pose when the frame arrived (map frame)."""
    source: str


@dataclass(frozen=True, slots=True)
class AnchoredRun:
    """The frames of one gap, each as a pose relative to the anchor frame's pose."""

    anchor_seq: int
    frames: tuple[tuple[int, float, Pose], ...]
    """(seq, stamp, pose in the anchor frame's robot frame)."""


@dataclass
class OffGraphTrack:
    """One robot's frames off the graph: the current gap, anchored gaps, settled frames,
    and the pose dead-reckoned from its last graph pose."""

    pending: list[OffGraphFrame] = field(default_factory=list)
    anchored: list[AnchoredRun] = field(default_factory=list)
    reckoned: Pose | None = None
    settled: list[OffGraphFrame] = field(default_factory=list)
    """Gap frames that could not be chained to an anchor: kept with the poses they had."""

    def on_graph(self, pose: Pose) -> None:
        """A frame the graph took: dead-reckoning restarts from its pose."""
        self.reckoned = pose

    def off_graph(
        self,
        *,
        seq: int,
        stamp: float,
        odometry: Pose | None,
        filter_pose: Pose,
        converged: bool,
    ) -> OffGraphFrame:
        """Keep a frame the graph did not take; returns it with its best pose."""
        last = self.reckoned
        reckoned = None if last is None or odometry is None else compose(last, odometry)
        if converged or reckoned is None:
            pose, source = filter_pose, FILTER
        else:
            pose, source = reckoned, ODOMETRY
        # Reckon on from a graph pose only: once the filter had to stand in, go on with it.
        self.reckoned = reckoned
        frame = OffGraphFrame(seq, stamp, odometry, pose, source)
        self.pending.append(frame)
        return frame

    def anchor(self, *, seq: int, odometry: Pose | None) -> None:
        """The frame `seq` (with `odometry` from the gap's last frame) anchors the chain:
        the gap's frames become poses relative to it, dead-reckoned backwards."""
        gap, self.pending = self.pending, []
        if not gap:
            return
        if odometry is None:  # a robot's first frame: nothing to chain back through
            self.settled.extend(gap)
            return
        rel = inverse(odometry)
        rows: list[tuple[int, float, Pose]] = []
        for k in range(len(gap) - 1, -1, -1):
            rows.append((gap[k].seq, gap[k].stamp, rel))
            step = gap[k].odometry
            if step is None:
                # The robot's first frame: everything before it is not part of this gap.
                break
            rel = compose(rel, inverse(step))
        rows.reverse()
        self.anchored.append(AnchoredRun(seq, tuple(rows)))

    def count(self) -> int:
        """Frames kept off the graph."""
        return sum(len(run.frames) for run in self.anchored) + len(self.settled) + len(self.pending)

    def rows(self, graph_poses: Mapping[int, Pose]) -> list[dict[str, Any]]:
        """Trajectory rows of the off-graph frames; `graph_poses` maps the robot's graph
        frames' seq to their current pose (for the anchored runs)."""
        out: list[dict[str, Any]] = []
        for run in self.anchored:
            base = graph_poses.get(run.anchor_seq)
            if base is None:
                continue
            for seq, stamp, rel in run.frames:
                x, y, theta = compose(base, rel)
                out.append(
                    {"seq": seq, "stamp": stamp, "x": x, "y": y, "theta": theta, "source": ODOMETRY}
                )
        for f in [*self.settled, *self.pending]:
            x, y, theta = f.pose
            out.append(
                {"seq": f.seq, "stamp": f.stamp, "x": x, "y": y, "theta": theta, "source": f.source}
            )
        return out

    def latest(self) -> OffGraphFrame | None:
        return self.pending[-1] if self.pending else None
