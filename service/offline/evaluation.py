"""The absolute trajectory error (ATE) and landmark errors of planar trajectories
(service.tum: the trajectory and its TUM files; its conventions), and the figures of a
map a service built from a simulated run (`map_figures`)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graph.angles import wrap_angles
from graph.types import FrameInput
from service.tum import Trajectory, read_tum, write_tum

if TYPE_CHECKING:
    import httpx

    from service.offline.datasets.indoor_sim import SimRun

__all__ = [
    "MapFit",
    "Trajectory",
    "align_se2",
    "associate",
    "ate_rmse",
    "dead_reckoning",
    "fit_landmarks",
    "interpolate",
    "landmark_errors",
    "read_tum",
    "write_tum",
]

FloatArray = NDArray[np.float64]


# --------------------------------------------------------------------------- interpolation


def interpolate(
    traj: Trajectory, stamps: ArrayLike, *, max_gap_s: float = math.inf
) -> tuple[NDArray[np.bool_], Trajectory]:
    """Interpolate a trajectory at query stamps.

    x, y are linear in time; theta is interpolated along the shorter arc between
    the two bracketing samples (unwrapped, then wrapped). A query is valid when
    it lies in ``[traj.stamps[0], traj.stamps[-1]]`` and, unless it coincides
    with a sample, the bracketing samples are at most `max_gap_s` apart.

    Args:
        traj: the trajectory, at least one pose.
        stamps: (M,) query stamps in seconds, any order.
        max_gap_s: the longest sample gap to interpolate across, seconds.

    Returns:
        (M,) bool mask of valid queries, and the Trajectory at the valid ones
        (in query order).
    """
    q = np.asarray(stamps, dtype=np.float64).reshape(-1)
    t = traj.stamps
    if len(t) == 0:
        return np.zeros(len(q), dtype=bool), Trajectory(np.empty(0), np.empty((0, 2)), np.empty(0))
    inside = (q >= t[0]) & (q <= t[-1])
    i0 = np.clip(np.searchsorted(t, q, side="right") - 1, 0, len(t) - 1)
    i1 = np.minimum(i0 + 1, len(t) - 1)
    exact = q == t[i0]
    gap = t[i1] - t[i0]
    valid = inside & (exact | (gap <= max_gap_s))
    i0, i1, qv, gap = i0[valid], i1[valid], q[valid], gap[valid]
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.where(gap > 0, (qv - t[i0]) / gap, 0.0)
    xy = traj.xy[i0] + s[:, None] * (traj.xy[i1] - traj.xy[i0])
    dtheta = wrap_angles(traj.theta[i1] - traj.theta[i0])
    theta = wrap_angles(traj.theta[i0] + s * dtheta)
    return valid, Trajectory(qv, xy, theta)


# --------------------------------------------------------------------------- ATE


def associate(
    est: Trajectory, gt: Trajectory, *, max_gap_s: float = 1.0
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Pair estimated positions with ground truth interpolated at the estimate's stamps.

    Estimate stamps outside the ground truth's span, or inside a ground-truth
    gap longer than `max_gap_s`, are dropped.

    Returns:
        stamps (K,), estimated xy (K, 2), ground-truth xy (K, 2).
    """
    valid, gt_at = interpolate(gt, est.stamps, max_gap_s=max_gap_s)
    return est.stamps[valid], est.xy[valid], gt_at.xy


def align_se2(src_xy: ArrayLike, dst_xy: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Least-squares rigid alignment in 2-D without scale (Umeyama / Kabsch).

    Finds the rotation R (2, 2) and translation t (2,) minimising
    ``sum_i |R @ src_i + t - dst_i|^2``.

    Args:
        src_xy: (K, 2) points to move, metres.
        dst_xy: (K, 2) target points, metres.
    """
    src = np.asarray(src_xy, dtype=np.float64).reshape(-1, 2)
    dst = np.asarray(dst_xy, dtype=np.float64).reshape(-1, 2)
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    cov = (dst - mu_d).T @ (src - mu_s)  # (2, 2) = sum d_i s_i^T
    u, _, vt = np.linalg.svd(cov)
    reflect = np.diag([1.0, 1.0 if np.linalg.det(u @ vt) >= 0.0 else -1.0])
    rot = u @ reflect @ vt
    return rot, mu_d - rot @ mu_s


def ate_rmse(
    est: Trajectory, gt: Trajectory, *, align: bool = False, max_gap_s: float = 1.0
) -> float:
    """Position RMSE (metres) of an estimate against ground truth.

    Ground truth is interpolated (linear in x, y) at the estimate's stamps; see
    `associate` for which stamps are kept. With ``align=True`` the estimate is
    first moved by the least-squares SE(2) alignment onto the ground truth.

    Raises:
        ValueError: fewer than 2 stamps overlap.
    """
    _, est_xy, gt_xy = associate(est, gt, max_gap_s=max_gap_s)
    if len(est_xy) < 2:
        raise ValueError(
            f"only {len(est_xy)} estimate stamps overlap the ground truth; need at least 2"
        )
    if align:
        rot, trans = align_se2(est_xy, gt_xy)
        est_xy = est_xy @ rot.T + trans
    return float(np.sqrt(np.mean(np.sum((est_xy - gt_xy) ** 2, axis=1))))


@dataclass(frozen=True)
class MapFit:
    """A map's landmarks judged against surveyed positions.

    The rigid motion (R, t) that best moves the estimated landmarks onto the surveyed
    ones (least squares, no scale) splits the map's error in two: where the map frame
    went (``rotation_rad``, and ``shift_m``, how far that motion moves the estimated
    landmarks' centroid: both zero for a map whose frame is the one the client gave)
    and the map's shape (``rmse_aligned_m``, after the motion). ``rmse_m`` is what a
    user of the map sees: the landmarks where the map puts them, in its own frame.

    Attributes:
        labels: the landmarks compared (in both sets), sorted.
        rotation_rad: rotation of the best fit, wrapped to (-pi, pi].
        shift_m: |R c + t - c| for the estimated landmarks' centroid c, metres.
        rmse_m: RMS distance estimated -> surveyed, unaligned, metres.
        rmse_aligned_m: RMS distance after the best rigid fit, metres.
        errors_aligned_m: each landmark's distance after the fit (``labels``' order), metres.
        motion: the fit itself, (R (2, 2), t (2,)): surveyed ~ R @ estimated + t.
        scale: the scale of the best similarity fit (the same rotation, and a scale):
            above 1, the map is smaller than the survey.
    """

    labels: tuple[str, ...]
    rotation_rad: float
    shift_m: float
    rmse_m: float
    rmse_aligned_m: float
    errors_aligned_m: tuple[float, ...]
    motion: tuple[NDArray[np.float64], NDArray[np.float64]]
    scale: float = 1.0

    def errors_by_label(self) -> dict[str, float]:
        """`errors_aligned_m` by landmark label, metres."""
        return dict(zip(self.labels, self.errors_aligned_m, strict=True))

    def as_dict(self) -> dict[str, float | int]:
        return {
            "landmarks": len(self.labels),
            "rotation_deg": math.degrees(self.rotation_rad),
            "shift_m": self.shift_m,
            "rmse_m": self.rmse_m,
            "rmse_aligned_m": self.rmse_aligned_m,
        }


def fit_landmarks(estimated: Mapping[str, ArrayLike], surveyed: Mapping[str, ArrayLike]) -> MapFit:
    """Compare landmark positions (x, y metres, by label) with surveyed ones.

    Only labels in both are compared; at least two are needed (ValueError otherwise).
    See `MapFit` for what each figure means."""
    labels = tuple(sorted(set(estimated) & set(surveyed)))
    if len(labels) < 2:
        raise ValueError(f"{len(labels)} landmarks in common with the survey; need at least 2")
    est = np.array([np.asarray(estimated[k], dtype=np.float64).reshape(2) for k in labels])
    ref = np.array([np.asarray(surveyed[k], dtype=np.float64).reshape(2) for k in labels])
    rot, trans = align_se2(est, ref)
    centroid = est.mean(axis=0)
    moved = est @ rot.T + trans
    errors = np.hypot(*(moved - ref).T)
    turned, centred = (est - centroid) @ rot.T, ref - ref.mean(axis=0)
    return MapFit(
        labels=labels,
        rotation_rad=math.atan2(float(rot[1, 0]), float(rot[0, 0])),
        shift_m=float(np.linalg.norm(rot @ centroid + trans - centroid)),
        rmse_m=float(np.sqrt(np.mean(np.sum((est - ref) ** 2, axis=1)))),
        rmse_aligned_m=float(np.sqrt(np.mean(errors**2))),
        errors_aligned_m=tuple(float(e) for e in errors),
        motion=(rot, trans),
        scale=float(np.sum(turned * centred) / np.sum(turned**2)),
    )


# --------------------------------------------------------------------------- dead reckoning


def dead_reckoning(frames: Sequence[FrameInput]) -> Trajectory:
    """Compose one robot's frame odometry from its first frame's initial pose.

    Pose i+1 = pose i (+) (dx, dy, dtheta) of frame i+1, where (dx, dy) is in
    the robot frame of pose i.

    Args:
        frames: one robot's frames in order; the first carries `initial_pose`,
            every later one carries `odometry`.

    Returns:
        The Trajectory at the frames' stamps, (len(frames),) poses.
    """
    if not frames:
        raise ValueError("no frames")
    first = frames[0]
    if first.initial_pose is None:
        raise ValueError(f"first frame (seq {first.seq}) has no initial_pose")
    rest = frames[1:]
    odo = np.zeros((len(rest), 3))
    for i, f in enumerate(rest):
        if f.robot != first.robot:
            raise ValueError(f"frames of two robots: {first.robot!r} and {f.robot!r}")
        if f.odometry is None:
            raise ValueError(f"frame seq {f.seq} has no odometry")
        odo[i] = (f.odometry.dx, f.odometry.dy, f.odometry.dtheta)
    p0 = first.initial_pose
    # Unwrapped heading after each frame; heading before frame i+1 is heading[i].
    heading = p0.theta + np.concatenate([[0.0], np.cumsum(odo[:, 2])])
    c, s = np.cos(heading[:-1]), np.sin(heading[:-1])
    step = np.column_stack([c * odo[:, 0] - s * odo[:, 1], s * odo[:, 0] + c * odo[:, 1]])
    origin = np.array([p0.x, p0.y])
    xy = np.vstack([origin, origin + np.cumsum(step, axis=0)])
    stamps = np.array([f.stamp for f in frames], dtype=np.float64)
    return Trajectory(stamps, xy, heading)


# --------------------------------------------------------------------------- landmarks


def landmark_errors(
    estimated_xy: Mapping[str, ArrayLike], true_xy: Mapping[str, ArrayLike]
) -> dict[str, float]:
    """Distance (metres) of each estimated landmark from its true position, by label.

    Unaligned: both in the map frame (judge a map's landmarks where it put them).
    Labels without a true position are left out.

    Args:
        estimated_xy: label -> (2,) estimated position, metres.
        true_xy: label -> (2,) true position, metres.
    """
    return {
        label: float(np.hypot(*(np.asarray(xy, dtype=np.float64) - np.asarray(true_xy[label]))))
        for label, xy in estimated_xy.items()
        if label in true_xy
    }


def map_figures(
    client: httpx.Client, map_id: str, run: SimRun, results: list[dict[str, Any]]
) -> dict[str, Any]:
    """What a map made of `run` (whose frame results are `results`): trees initialised
    (distinct labels) and landmark ids the frames added, ATE, live landmarks' errors."""
    summary = client.get(f"/v1/maps/{map_id}").json()
    counts = summary["counts"]
    # stats_every beyond the run: the latest pose alone carries the frame's figures.
    traj = client.get(f"/v1/maps/{map_id}/trajectory", params={"stats_every": 1_000_000})
    rows = traj.json()["robots"]["r1"]
    est = Trajectory.from_poses(
        [p["stamp"] for p in rows], [[p["x"], p["y"], p["theta"]] for p in rows]
    )
    truth = {str(i): xy for i, xy in zip(run.landmark_ids.tolist(), run.landmarks, strict=True)}
    landmarks = client.get(f"/v1/maps/{map_id}/landmarks").json()
    errors = landmark_errors({m["label"]: (m["x"], m["y"]) for m in landmarks}, truth)
    err = np.array(list(errors.values()))
    observed = {o.label for f in run.frames for o in f.observations}
    return {
        "map_id": map_id,
        "config": summary["config"],
        "trees": len(truth),
        "trees_observed": len(observed),
        # A capped map re-initialises a removed tree seen again under a new id: count trees.
        "trees_initialised": rows[-1]["uncapped"],
        "landmark_initialisations": len({i for r in results for i in r["landmarks"]["added"]}),
        "landmarks_live": counts["live_landmarks"],
        "ate_rmse_m": ate_rmse(est, run.ground_truth),
        "ate_rmse_aligned_m": ate_rmse(est, run.ground_truth, align=True),
        "landmark_rmse_m": float(np.sqrt(np.mean(err**2))) if len(err) else None,
        "landmark_max_error_m": float(err.max()) if len(err) else None,
    }
