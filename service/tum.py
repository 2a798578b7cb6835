"""Planar trajectories and TUM files.

Convention: a trajectory is a sequence of planar poses in the map frame:
stamps in seconds, positions in metres, yaw theta in radians CCW from +x,
wrapped to (-pi, pi]. In TUM files a planar pose is ``stamp x y 0 0 0 qz qw``
with the rotation about +z: ``qz = sin(theta/2)``, ``qw = cos(theta/2)``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graph.angles import wrap_angles

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Trajectory:
    """Planar poses at increasing stamps.

    Attributes:
        stamps: (N,) seconds, non-decreasing.
        xy: (N, 2) positions in metres.
        theta: (N,) yaw in radians, wrapped to (-pi, pi].
    """

    stamps: FloatArray
    xy: FloatArray
    theta: FloatArray

    def __post_init__(self) -> None:
        stamps = np.asarray(self.stamps, dtype=np.float64).reshape(-1)
        xy = np.asarray(self.xy, dtype=np.float64).reshape(-1, 2)
        theta = wrap_angles(np.asarray(self.theta, dtype=np.float64).reshape(-1))
        if not (len(stamps) == len(xy) == len(theta)):
            raise ValueError(
                f"stamps {stamps.shape}, xy {xy.shape} and theta {theta.shape} differ in length"
            )
        if np.any(np.diff(stamps) < 0):
            raise ValueError("stamps must be non-decreasing")
        object.__setattr__(self, "stamps", stamps)
        object.__setattr__(self, "xy", xy)
        object.__setattr__(self, "theta", theta)

    def __len__(self) -> int:
        return len(self.stamps)

    @classmethod
    def from_poses(cls, stamps: ArrayLike, poses_xytheta: ArrayLike) -> Trajectory:
        """Build from (N,) stamps and (N, 3) poses ``[x, y, theta]``."""
        poses = np.asarray(poses_xytheta, dtype=np.float64).reshape(-1, 3)
        return cls(np.asarray(stamps, dtype=np.float64), poses[:, :2], poses[:, 2])

    def poses(self) -> FloatArray:
        """(N, 3) ``[x, y, theta]``."""
        return np.column_stack([self.xy, self.theta])


# --------------------------------------------------------------------------- TUM files


def write_tum(path: str | os.PathLike[str], traj: Trajectory) -> None:
    """Write ``stamp x y z qx qy qz qw`` lines (z = qx = qy = 0), all ``%.6f``."""
    half = 0.5 * traj.theta
    zeros = np.zeros(len(traj))
    table = np.column_stack([traj.stamps, traj.xy, zeros, zeros, zeros, np.sin(half), np.cos(half)])
    np.savetxt(path, table, fmt="%.6f", header="stamp x y z qx qy qz qw", comments="# ")


def read_tum(path: str | os.PathLike[str]) -> Trajectory:
    """Read a TUM trajectory; '#' starts a comment. Yaw is taken from the full quaternion."""
    table = np.loadtxt(path, comments="#", ndmin=2, dtype=np.float64)
    if table.size == 0:
        table = table.reshape(0, 8)
    if table.shape[1] != 8:
        raise ValueError(
            f"{path}: expected 8 columns (stamp x y z qx qy qz qw), got {table.shape[1]}"
        )
    qx, qy, qz, qw = table[:, 4], table[:, 5], table[:, 6], table[:, 7]
    yaw = np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
    return Trajectory(table[:, 0], table[:, 1:3], yaw)
