"""Full batch Levenberg-Marquardt over every frame: the accuracy reference.

Same factors as the online map (odometry noise model, bearing noise, Huber),
every landmark and every pose kept. Landmarks are initialised by triangulating
all their rays from dead-reckoning poses; the online estimate can be given as a
second starting point, and the solution with the lower final cost is kept (the
choice never looks at ground truth).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import gtsam
import numpy as np
from numpy.typing import NDArray

from graph.angles import wrap_angles
from graph.config import SlamConfig
from graph.factors import (
    bearing_factor,
    landmark_key,
    odometry_factor,
    pose_key,
    pose_prior_factor,
)
from graph.triangulation import triangulate
from graph.types import FrameInput
from service.offline.evaluation import Trajectory, dead_reckoning


@dataclass(frozen=True)
class BatchResult:
    trajectory: Trajectory
    cost: float
    start: str
    """Which starting point won: 'dead_reckoning', 'online' or 'online_<name>'."""
    landmarks: int
    landmark_xy: dict[str, tuple[float, float]] = field(default_factory=dict)
    """The solution's landmark positions (x, y metres) by label."""
    per_start: dict[str, BatchResult] = field(default_factory=dict)
    """The winner only: the solution from every starting point that converged, by name."""
    landmark_cov: dict[str, NDArray[np.float64]] = field(default_factory=dict)
    """With `batch_solve(..., covariances=True)`, the winner's landmark marginal
    covariances (2x2, m^2) by label (gtsam.Marginals of the whole graph)."""


def _xy(point: np.ndarray) -> tuple[float, float]:
    return float(point[0]), float(point[1])


def batch_graph(frames: Sequence[FrameInput], config: SlamConfig, labels: dict[str, int]):
    """Every factor of a robot's run (its first pose's prior, odometry, bearings to the
    landmarks `labels` numbers), as the batch solves them."""
    graph = gtsam.NonlinearFactorGraph()
    for k, f in enumerate(frames):
        key = pose_key(0, k)
        if k == 0:
            assert f.initial_pose is not None
            graph.add(pose_prior_factor(key, f.initial_pose, config))
        else:
            assert f.odometry is not None
            graph.add(
                odometry_factor(
                    pose_key(0, k - 1), key, f.odometry, config, f.stamp - frames[k - 1].stamp
                )
            )
        for o in f.observations:
            if o.label in labels:
                sigma = o.sigma_rad or config.bearing_sigma_rad
                graph.add(
                    bearing_factor(
                        key, landmark_key(labels[o.label]), o.bearing_rad, sigma, config.huber_k
                    )
                )
    return graph


def batch_solve(
    frames: Sequence[FrameInput],
    config: SlamConfig,
    *,
    online: Trajectory | dict[str, Trajectory] | None = None,
    covariances: bool = False,
) -> BatchResult:
    """Optimise all frames of one robot at once, from dead reckoning and from each
    online estimate given; the solution with the lowest graph error wins (LM finds a
    local minimum, and a bearing-only graph has bad ones). `covariances`: the winner
    also carries its landmarks' marginal covariances."""
    dr = dead_reckoning(frames)
    # Every ray of a label: (frame index, bearing, sigma); origins come from the start.
    rays: dict[str, list[tuple[int, float, float]]] = {}
    for k, f in enumerate(frames):
        for o in f.observations:
            rays.setdefault(o.label, []).append(
                (k, o.bearing_rad, o.sigma_rad or config.bearing_sigma_rad)
            )
    starts: dict[str, Trajectory] = {"dead_reckoning": dr}
    if isinstance(online, Trajectory):
        starts["online"] = online
    elif online is not None:
        starts.update({f"online_{name}": t for name, t in online.items()})
    labels: dict[str, int] = {}
    solved: dict[str, BatchResult] = {}
    problems: dict[str, tuple[gtsam.NonlinearFactorGraph, gtsam.Values, dict[str, int]]] = {}
    for name, start in starts.items():
        values = gtsam.Values()
        for k in range(len(frames)):
            x, y = start.xy[k]
            values.insert(pose_key(0, k), gtsam.Pose2(float(x), float(y), float(start.theta[k])))
        for label, rr in rays.items():
            idx = np.array([k for k, _, _ in rr])
            bearings = np.array([b for _, b, _ in rr])
            r = np.column_stack(
                [
                    start.xy[idx],
                    wrap_angles(start.theta[idx] + bearings),
                    [s for _, _, s in rr],
                ]
            )
            tri = triangulate(r[:, :2], r[:, 2], r[:, 3]) if len(r) >= 2 else None
            if tri is None:
                continue
            labels.setdefault(label, len(labels))
            values.insert(landmark_key(labels[label]), tri.point)
        graph = batch_graph(
            frames, config, {lb: i for lb, i in labels.items() if values.exists(landmark_key(i))}
        )
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(200)
        try:
            est = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        except RuntimeError:
            continue
        poses = np.array(
            [
                [
                    est.atPose2(pose_key(0, k)).x(),
                    est.atPose2(pose_key(0, k)).y(),
                    est.atPose2(pose_key(0, k)).theta(),
                ]
                for k in range(len(frames))
            ]
        )
        result = BatchResult(
            Trajectory.from_poses(dr.stamps, poses),
            graph.error(est),
            name,
            sum(1 for i in labels.values() if est.exists(landmark_key(i))),
            {
                label: _xy(est.atPoint2(landmark_key(i)))
                for label, i in labels.items()
                if est.exists(landmark_key(i))
            },
        )
        solved[name] = result
        problems[name] = (graph, est, labels)
        labels = {}
    if not solved:
        raise RuntimeError("batch optimisation failed from every starting point")
    best = min(solved.values(), key=lambda r: r.cost)
    cov: dict[str, NDArray[np.float64]] = {}
    if covariances:
        graph, est, used = problems[best.start]
        marginals = gtsam.Marginals(graph, est)
        cov = {
            label: np.asarray(marginals.marginalCovariance(landmark_key(i)), dtype=np.float64)
            for label, i in used.items()
            if est.exists(landmark_key(i))
        }
    return replace(best, per_start=solved, landmark_cov=cov)
