"""UTIAS MRCLAM (Leung et al., IJRR 2011) as covslam frames, built on the fly.

Used bearing-only: ranges are dropped, and so are measurements of other robots
(subjects 1-5) and of barcodes that are in no table. Ground truth (Vicon) is
returned separately, for evaluation only.

Convention (MRCLAM, checked against ground truth in the tests): bearings are
radians in the robot frame, counter-clockwise from the forward axis; odometry
samples are (t [s], v [m/s], omega [rad/s]) of a unicycle, and each sample holds
until the next sample's time.

Tables are the dataset's whitespace files, plain or gzip (``.dat`` or
``.dat.gz``); '#' starts a comment.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graph.angles import wrap_angles
from graph.types import BearingObservation, FrameInput, Odometry, Pose2D
from service.offline.evaluation import Trajectory, dead_reckoning, interpolate

__all__ = [
    "ROBOT_SUBJECTS",
    "MrclamRobot",
    "dead_reckoning",
    "default_data_dir",
    "default_mrclam_dir",
    "integrate_unicycle",
    "load_mrclam",
    "measurement_rate_hz",
    "mrclam_frames",
    "mrclam_noise",
    "relative_motion",
    "surveyed_landmarks",
]

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

ROBOT_SUBJECTS = frozenset(range(1, 6))
"""MRCLAM subject numbers of the robots; 6-20 are landmarks."""


def default_data_dir() -> Path:
    """The evaluation data directory: ``$COVSLAM_DATA``, else ``<repo>/../shared/data``.

    Read at call time. The fallback assumes a source checkout (``<repo>`` is the
    directory holding ``service/``).
    """
    env = os.environ.get("COVSLAM_DATA")
    if env:
        return Path(env)
    repo = Path(__file__).resolve().parents[3]
    return repo.parent / "shared" / "data"


def default_mrclam_dir() -> Path:
    """``default_data_dir() / "mrclam6"`` (MRCLAM dataset 6)."""
    return default_data_dir() / "mrclam6"


@dataclass(frozen=True)
class MrclamRobot:
    """One robot's tables of one MRCLAM dataset, sorted by time.

    Attributes:
        robot: robot number 1-5.
        odometry: (K, 3) ``[t s, v m/s, omega rad/s]``.
        measurements: (M, 4) ``[t s, barcode, range m, bearing rad]``, all of them.
        groundtruth: (G, 4) ``[t s, x m, y m, theta rad]``.
        barcodes: (S, 2) int ``[subject, barcode]``.
        landmarks: (L, 3) ``[subject, x m, y m]`` landmark ground truth, or None
            when ``Landmark_Groundtruth.dat`` is absent.
    """

    robot: int
    odometry: FloatArray
    measurements: FloatArray
    groundtruth: FloatArray
    barcodes: NDArray[np.int64]
    landmarks: FloatArray | None = None


def _find_table(directory: Path, stem: str) -> Path | None:
    for name in (f"{stem}.dat", f"{stem}.dat.gz"):
        path = directory / name
        if path.is_file():
            return path
    return None


def _load_table(directory: Path, stem: str, columns: int) -> FloatArray:
    path = _find_table(directory, stem)
    if path is None:
        raise FileNotFoundError(f"{directory}: neither {stem}.dat nor {stem}.dat.gz")
    table = np.loadtxt(path, comments="#", ndmin=2, dtype=np.float64)
    if table.size == 0:
        table = table.reshape(0, columns)
    if table.shape[1] != columns:
        raise ValueError(f"{path}: expected {columns} columns, got {table.shape[1]}")
    return table


def _sorted_by_time(table: FloatArray) -> FloatArray:
    return table[np.argsort(table[:, 0], kind="stable")]


def load_mrclam(directory: str | os.PathLike[str], robot: int) -> MrclamRobot:
    """Read robot `robot`'s odometry, measurements and ground truth, and the barcodes."""
    if robot not in ROBOT_SUBJECTS:
        raise ValueError(f"robot must be one of 1-5, got {robot}")
    d = Path(directory)
    landmarks = None
    if _find_table(d, "Landmark_Groundtruth") is not None:
        landmarks = _load_table(d, "Landmark_Groundtruth", 5)[:, :3]
    return MrclamRobot(
        robot=robot,
        odometry=_sorted_by_time(_load_table(d, f"Robot{robot}_Odometry", 3)),
        measurements=_sorted_by_time(_load_table(d, f"Robot{robot}_Measurement", 4)),
        groundtruth=_sorted_by_time(_load_table(d, f"Robot{robot}_Groundtruth", 4)),
        barcodes=_load_table(d, "Barcodes", 2).astype(np.int64),
        landmarks=landmarks,
    )


def surveyed_landmarks(directory: str | os.PathLike[str]) -> dict[str, FloatArray]:
    """The surveyed landmark positions (x, y metres, map frame of the ground truth) by
    the label `mrclam_frames` gives their observations (the subject number)."""
    table = _load_table(Path(directory), "Landmark_Groundtruth", 5)
    return {str(int(row[0])): row[1:3].copy() for row in table}


# --------------------------------------------------------------------------- odometry


def _chord(v: FloatArray, w: FloatArray, dt: FloatArray, theta: FloatArray) -> FloatArray:
    """Displacement (n, 2) of a unicycle at constant (v, w) for dt from heading theta.

    Exact for every w: the chord has length ``2 v/w sin(w dt/2) = v dt sinc(w dt/2)``
    and direction ``theta + w dt/2``; at w = 0 this is the straight line v dt.
    """
    half = 0.5 * w * dt
    length = v * dt * np.sinc(half / np.pi)  # np.sinc(x) = sin(pi x)/(pi x)
    direction = theta + half
    return np.column_stack([length * np.cos(direction), length * np.sin(direction)])


def integrate_unicycle(odometry: ArrayLike, stamps: ArrayLike) -> FloatArray:
    """Integrate piecewise-constant unicycle odometry exactly and sample it at stamps.

    Args:
        odometry: (K, 3) ``[t s, v m/s, omega rad/s]`` sorted by t; each sample
            holds until the next sample's time (the last one indefinitely).
        stamps: (F,) query times in seconds, each >= ``odometry[0, 0]``.

    Returns:
        (F, 3) poses ``[x m, y m, theta rad]`` relative to the pose at the first
        odometry sample (origin, heading 0); theta is not wrapped (continuous).
    """
    odo = np.asarray(odometry, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(stamps, dtype=np.float64).reshape(-1)
    if len(odo) == 0:
        raise ValueError("no odometry samples")
    t, v, w = odo[:, 0], odo[:, 1], odo[:, 2]
    if np.any(q < t[0]):
        raise ValueError("a stamp lies before the first odometry sample")
    dt = np.diff(t)
    theta_k = np.concatenate([[0.0], np.cumsum(w[:-1] * dt)])  # heading at each sample
    xy_k = np.vstack([[0.0, 0.0], np.cumsum(_chord(v[:-1], w[:-1], dt, theta_k[:-1]), axis=0)])
    k = np.clip(np.searchsorted(t, q, side="right") - 1, 0, len(t) - 1)
    tau = q - t[k]
    xy = xy_k[k] + _chord(v[k], w[k], tau, theta_k[k])
    return np.column_stack([xy, theta_k[k] + w[k] * tau])


def relative_motion(poses_xytheta: ArrayLike) -> FloatArray:
    """Motion between consecutive poses, in the earlier pose's frame.

    Args:
        poses_xytheta: (F, 3) poses ``[x, y, theta]``.

    Returns:
        (F - 1, 3) ``[dx m, dy m, dtheta rad]`` with dtheta wrapped to (-pi, pi].
    """
    p = np.asarray(poses_xytheta, dtype=np.float64).reshape(-1, 3)
    d = np.diff(p, axis=0)
    c, s = np.cos(p[:-1, 2]), np.sin(p[:-1, 2])
    return np.column_stack(
        [c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], wrap_angles(d[:, 2])]
    )


# --------------------------------------------------------------------------- frames


def _group_starts(times: FloatArray, tol_s: float) -> list[int]:
    """Indices where a new group starts: a time more than tol_s after its group's first."""
    starts = [0]
    for i in range(1, len(times)):
        if times[i] - times[starts[-1]] > tol_s:
            starts.append(i)
    return starts


def _fill_gaps(
    stamps: FloatArray, end_s: float, max_gap_s: float
) -> tuple[FloatArray, NDArray[np.int64]]:
    """Add stamps so that no gap exceeds max_gap_s, up to end_s.

    A gap between two stamps is split into equal parts; after the last stamp,
    stamps follow every max_gap_s while they are <= end_s.

    Returns:
        (F,) all stamps, and (F,) the index into `stamps` of each, -1 for added ones.
    """
    out: list[float] = [float(stamps[0])]
    source: list[int] = [0]
    for i in range(1, len(stamps)):
        a, b = float(stamps[i - 1]), float(stamps[i])
        parts = math.ceil((b - a) / max_gap_s)
        out.extend(a + (b - a) * j / parts for j in range(1, parts))
        source.extend([-1] * (parts - 1))
        out.append(b)
        source.append(i)
    tail = out[-1] + max_gap_s
    while tail <= end_s:
        out.append(tail)
        source.append(-1)
        tail += max_gap_s
    return np.asarray(out), np.asarray(source, dtype=np.int64)


MRCLAM_HEADING_DRIFT_RAD_PER_SQRT_S = math.radians(2.0)
"""Heading random walk of MRCLAM's wheel odometry. ../shared/data/README.md
reports a heading error of about 6-10 degrees RMS per 10 s, which a
motion-proportional model alone cannot express; 2 deg/sqrt(s) gives 6.3 deg
per 10 s."""


def mrclam_noise() -> dict[str, Any]:
    """SlamConfig fields for MRCLAM's odometry (time-based heading drift)."""
    return {"odometry_sigma_per_sqrt_second": (0.0, 0.0, MRCLAM_HEADING_DRIFT_RAD_PER_SQRT_S)}


def mrclam_frames(
    data: MrclamRobot,
    *,
    bearing_sigma_rad: float = float(np.deg2rad(1.0)),
    max_gap_s: float = 1.0,
    group_tol_s: float = 1e-3,
) -> tuple[list[FrameInput], Trajectory]:
    """Bearing-only frames of one MRCLAM robot, and its ground truth.

    One frame per distinct landmark-measurement time (times within
    `group_tol_s` of a frame's first measurement join it; a repeated label in
    one frame keeps the first), plus odometry-only frames so that no more than
    `max_gap_s` passes between frames. Frames start at the first landmark
    measurement at which odometry and ground truth both exist and stop at the
    end of ground truth (or of odometry, if earlier). The first frame carries
    `initial_pose` = ground truth interpolated at its stamp and no odometry;
    every later frame carries the exactly integrated odometry since the
    previous frame (sigmas left to the map's noise model). Observations carry
    `bearing_sigma_rad` and the landmark's subject number as label.

    Returns:
        Frames (robot ``"r{N}"``, seq 0, 1, ..., stamp = dataset time in s) and
        the ground truth from the sample at or before the first frame to the end.
    """
    gt = Trajectory(data.groundtruth[:, 0], data.groundtruth[:, 1:3], data.groundtruth[:, 3])
    odo = data.odometry
    if len(gt) == 0 or len(odo) == 0:
        raise ValueError(f"robot {data.robot}: no ground truth or no odometry")
    start_s = max(float(odo[0, 0]), float(gt.stamps[0]))
    end_s = min(float(odo[-1, 0]), float(gt.stamps[-1]))

    subject_of = {int(b): int(s) for s, b in data.barcodes}
    meas = data.measurements
    subjects = np.array([subject_of.get(int(b), -1) for b in meas[:, 1]], dtype=np.int64)
    is_landmark = (subjects > 0) & ~np.isin(subjects, list(ROBOT_SUBJECTS))
    in_span = (meas[:, 0] >= start_s) & (meas[:, 0] <= end_s)
    keep = is_landmark & in_span
    logger.info(
        "robot %d: %d measurements, %d of robots, %d of unknown barcodes, %d outside span, %d kept",
        data.robot,
        len(meas),
        int(np.isin(subjects, list(ROBOT_SUBJECTS)).sum()),
        int((subjects < 0).sum()),
        int((is_landmark & ~in_span).sum()),
        int(keep.sum()),
    )
    meas, subjects = meas[keep], subjects[keep]
    if len(meas) == 0:
        raise ValueError(f"robot {data.robot}: no landmark measurement within odometry and gt")

    starts = _group_starts(meas[:, 0], group_tol_s)
    bearings = wrap_angles(meas[:, 3])
    groups: list[tuple[BearingObservation, ...]] = []
    for g, i0 in enumerate(starts):
        i1 = starts[g + 1] if g + 1 < len(starts) else len(meas)
        seen: dict[str, BearingObservation] = {}
        for i in range(i0, i1):
            label = str(subjects[i])
            if label not in seen:
                seen[label] = BearingObservation(
                    bearing_rad=float(bearings[i]), label=label, sigma_rad=bearing_sigma_rad
                )
        groups.append(tuple(seen.values()))

    stamps, source = _fill_gaps(meas[starts, 0], end_s, max_gap_s)
    motion = relative_motion(integrate_unicycle(odo, stamps))
    _, first = interpolate(gt, stamps[:1])
    robot = f"r{data.robot}"
    frames: list[FrameInput] = []
    for seq, (stamp, src) in enumerate(zip(stamps, source, strict=True)):
        observations = groups[src] if src >= 0 else ()
        if seq == 0:
            pose = Pose2D(float(first.xy[0, 0]), float(first.xy[0, 1]), float(first.theta[0]))
            frames.append(
                FrameInput(
                    robot=robot,
                    seq=0,
                    stamp=float(stamp),
                    initial_pose=pose,
                    observations=observations,
                )
            )
            continue
        dx, dy, dtheta = (float(x) for x in motion[seq - 1])
        frames.append(
            FrameInput(
                robot=robot,
                seq=seq,
                stamp=float(stamp),
                odometry=Odometry(dx=dx, dy=dy, dtheta=dtheta),
                observations=observations,
            )
        )

    i0 = max(int(np.searchsorted(gt.stamps, stamps[0], side="right")) - 1, 0)
    i1 = int(np.searchsorted(gt.stamps, end_s, side="right"))
    truth = Trajectory(gt.stamps[i0:i1], gt.xy[i0:i1], gt.theta[i0:i1])
    return frames, truth


def measurement_rate_hz(frames: Sequence[FrameInput]) -> float:
    """Landmark bearings per second over the frames' time span."""
    if len(frames) < 2:
        return 0.0
    count = sum(len(f.observations) for f in frames)
    return count / (frames[-1].stamp - frames[0].stamp)
