"""Tracked frames: composed odometry, the pose solve, and frames kept out of the graph."""

from __future__ import annotations

import dataclasses
import math

import gtsam
import numpy as np
import pytest

from graph.config import SlamConfig
from graph.factors import landmark_key, pose_key
from graph.slam import BearingSlam
from graph.snapshot import capture, restore
from graph.tracking import Motion, compose_motion, solve_pose, tracked_covariance
from graph.types import Pose2D
from tests.graph._world import circle_frames

STEPS = [(0.12, 0.01, 0.05), (0.10, -0.02, -0.2), (0.0, 0.0, 0.4), (0.15, 0.03, 0.1)]
SIGMAS = [(0.01, 0.02, 0.01), (0.02, 0.01, 0.03), (0.005, 0.005, 0.02), (0.03, 0.01, 0.01)]


def _rmse(traj: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((traj[:, 2:4] - truth[:, :2]) ** 2, axis=1))))


def test_composed_odometry_equals_gtsams_chain_marginal() -> None:
    """The composed motion and covariance are those of the last pose of a chain of
    BetweenFactorPose2 from a pose held fixed (GTSAM's own marginal)."""
    motion: Motion | None = None
    for step, sig in zip(STEPS, SIGMAS, strict=True):
        motion = compose_motion(motion, step, np.array(sig))
    assert motion is not None and motion.frames == len(STEPS)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(3, 1e-9)))
    values.insert(0, gtsam.Pose2())
    pose = gtsam.Pose2()
    for k, (step, sig) in enumerate(zip(STEPS, SIGMAS, strict=True), start=1):
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.array(sig))
        graph.add(gtsam.BetweenFactorPose2(k - 1, k, gtsam.Pose2(*step), noise))
        pose = pose.compose(gtsam.Pose2(*step))
        values.insert(k, pose)
    marginal = gtsam.Marginals(graph, values).marginalCovariance(len(STEPS))
    np.testing.assert_allclose(motion.xyt, (pose.x(), pose.y(), pose.theta()), atol=1e-12)
    np.testing.assert_allclose(motion.covariance, marginal, rtol=1e-6, atol=1e-12)


def _pose_problem(seed: int) -> tuple[gtsam.Pose2, gtsam.Pose2, Motion, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    base = gtsam.Pose2(1.0, -2.0, 0.3)
    motion = compose_motion(None, (0.3, 0.05, 0.2), np.array([0.05, 0.05, 0.05]))
    truth = base.compose(motion.pose).compose(gtsam.Pose2(0.03, -0.02, 0.01))
    xy = rng.uniform(-6, 6, (12, 2))
    bearings = np.array(
        [truth.bearing(gtsam.Point2(*p)).theta() + rng.normal(0, 0.002) for p in xy]
    )
    return base, truth, motion, xy, bearings


@pytest.mark.parametrize("seed", range(4))
def test_the_pose_solve_equals_gtsam_with_the_landmarks_fixed(seed: int) -> None:
    """Without the robust loss, the solve is the MAP of a graph with the prior at
    base (+) motion and the bearings to landmarks held fixed; its covariance is GTSAM's
    marginal of that graph."""
    base, truth, motion, xy, bearings = _pose_problem(seed)
    sigma = 0.002
    solved = solve_pose(base, motion, xy, bearings, np.full(len(xy), sigma), None)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    prior = base.compose(motion.pose)
    graph.add(
        gtsam.PriorFactorPose2(0, prior, gtsam.noiseModel.Gaussian.Covariance(motion.covariance))
    )
    values.insert(0, prior)
    for i, (p, z) in enumerate(zip(xy, bearings, strict=True)):
        key = landmark_key(i)
        graph.add(
            gtsam.PriorFactorPoint2(
                key, gtsam.Point2(*p), gtsam.noiseModel.Isotropic.Sigma(2, 1e-9)
            )
        )
        graph.add(
            gtsam.BearingFactor2D(0, key, gtsam.Rot2(z), gtsam.noiseModel.Isotropic.Sigma(1, sigma))
        )
        values.insert(key, gtsam.Point2(*p))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-14)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    expected = result.atPose2(0)
    assert solved.pose.equals(expected, 1e-7)
    assert math.hypot(solved.pose.x() - truth.x(), solved.pose.y() - truth.y()) < 0.01
    np.testing.assert_allclose(
        solved.covariance,
        gtsam.Marginals(graph, result).marginalCovariance(0),
        rtol=1e-3,
        atol=1e-12,
    )
    # With the base pose certain, the full covariance is the conditional one.
    np.testing.assert_allclose(
        tracked_covariance(np.zeros((3, 3)), motion, solved.information),
        solved.covariance,
        rtol=1e-3,
        atol=1e-12,
    )


def test_the_robust_loss_shrugs_off_a_wrong_bearing() -> None:
    base, _, motion, xy, bearings = _pose_problem(9)
    bad = bearings.copy()
    bad[0] += 0.5
    sigmas = np.full(len(xy), 0.002)
    plain = solve_pose(base, motion, xy, bad, sigmas, None).pose
    robust = solve_pose(base, motion, xy, bad, sigmas, 1.345).pose
    clean = solve_pose(base, motion, xy, bearings, sigmas, 1.345).pose

    def dist(a: gtsam.Pose2, b: gtsam.Pose2) -> float:
        return math.hypot(a.x() - b.x(), a.y() - b.y())

    assert dist(robust, clean) < 0.25 * dist(plain, clean)


CFG = SlamConfig(
    landmark_cap=12,
    pose_window=15,
    window_observations=None,
    max_keyframes=6,
    # The circle world turns all the time with odometry ~10x better than a wheeled
    # robot's: the default model's heading random walk per radian turned (5 deg) would
    # weigh the dead reckoning tracked frames hang from below what this world deserves.
    odometry_sigma_per_sqrt_radian=0.0,
)


def _tracked(distance: float, **kw: object) -> SlamConfig:
    return dataclasses.replace(CFG, graph_frame_distance_m=distance, **kw)  # type: ignore[arg-type]


def test_off_by_default_every_frame_enters_the_graph() -> None:
    frames, _, _ = circle_frames(40, seed=1, n_landmarks=25)
    slam = BearingSlam(CFG, rng=np.random.default_rng(0))
    for f in frames:
        assert slam.process(f, with_covariance=False).timing_ms["update"] > 0
    assert slam._robots["r1"].next_index == len(frames)


def test_tracked_frames_stay_out_of_the_graph_and_follow_it() -> None:
    """With graph frames every 0.4 m (0.15 m a frame), about one frame in three enters
    the graph; every frame is in the trajectory, tracked frames move with the graph
    pose they hang from, and the run is about as accurate as one with every frame."""
    frames, truth, _ = circle_frames(300, seed=2, n_landmarks=30)
    slam = BearingSlam(_tracked(0.4), rng=np.random.default_rng(0))
    in_graph = 0
    for k, f in enumerate(frames):
        out = slam.process(f, with_covariance=True)
        tracked = out.timing_ms["update"] == 0.0
        in_graph += not tracked
        assert out.covariance is not None and np.all(np.linalg.eigvalsh(out.covariance) > 0)
        if tracked:
            # The newest frame's pose as the map reports it is the frame's result (a
            # graph frame's moves a little with the landmark budget's update after it).
            latest = slam.latest_pose("r1")
            assert abs(latest.x() - out.pose.x) < 1e-9 and abs(latest.y() - out.pose.y) < 1e-9
            np.testing.assert_allclose(slam.latest_pose_covariance("r1"), out.covariance)
            # No landmark of its own (its outcome lists the removals of the upkeep
            # after the graph frame before it).
            assert out.added == ()
            assert math.hypot(out.pose.x - truth[k, 0], out.pose.y - truth[k, 1]) < 0.3
    assert 0.25 * len(frames) < in_graph < 0.5 * len(frames)
    assert slam._robots["r1"].next_index == in_graph
    traj = slam.trajectory()["r1"]
    assert len(traj) == len(frames)
    np.testing.assert_array_equal(traj[:, 0], [f.seq for f in frames])
    every = BearingSlam(CFG, rng=np.random.default_rng(0))
    for f in frames:
        every.process(f, with_covariance=False)
    assert _rmse(traj, truth) < 1.5 * _rmse(every.trajectory()["r1"], truth) + 0.02
    # Neighbouring frames stay neighbours after the window's exits (no frame left behind
    # at a stale estimate).
    steps = np.hypot(*np.diff(traj[:, 2:4], axis=0).T)
    assert steps.max() < 0.3


def test_a_frame_with_few_landmarks_or_a_long_gap_enters_the_graph() -> None:
    frames, _, _ = circle_frames(60, seed=3, n_landmarks=25)
    slam = BearingSlam(_tracked(100.0, graph_frame_max_gap=3), rng=np.random.default_rng(0))
    kinds = [slam.process(f, with_covariance=False).timing_ms["update"] > 0 for f in frames]
    # Far beyond the distance: a graph frame every third frame once landmarks are live.
    assert kinds[-9:] == [False, False, True] * 3
    blind = dataclasses.replace(frames[-1], seq=1000, stamp=1000.0, observations=())
    assert slam.process(blind, with_covariance=False).timing_ms["update"] > 0


def test_an_anchor_restarts_the_chain_from_a_graph_frame() -> None:
    frames, truth, _ = circle_frames(50, seed=4, n_landmarks=25)
    slam = BearingSlam(_tracked(100.0), rng=np.random.default_rng(0))
    for f in frames[:-1]:
        slam.process(f, with_covariance=False)
    assert slam._robots["r1"].motion is not None
    x, y, th = truth[-1]
    out = slam.process(
        frames[-1], with_covariance=False, anchor=(Pose2D(x, y, th), np.diag([0.01, 0.01, 0.01]))
    )
    assert out.timing_ms["update"] > 0
    assert slam._robots["r1"].motion is None and slam._robots["r1"].tracked is None
    assert pose_key(0, slam._robots["r1"].next_index - 1) in slam.graph


def test_a_snapshot_between_graph_frames_restores_the_tracking_state() -> None:
    frames, _, _ = circle_frames(140, seed=5, n_landmarks=25)
    original = BearingSlam(_tracked(0.4), rng=np.random.default_rng(0))
    for f in frames[:101]:
        original.process(f, with_covariance=False)
    restored = restore(capture(original))
    for f in frames[101:]:
        a = original.process(f, with_covariance=False)
        b = restored.process(f, with_covariance=False)
        assert (a.timing_ms["update"] > 0) == (b.timing_ms["update"] > 0)
        assert a.observed == b.observed
        assert abs(a.pose.x - b.pose.x) < 0.02 and abs(a.pose.y - b.pose.y) < 0.02
    np.testing.assert_allclose(restored.trajectory()["r1"], original.trajectory()["r1"], atol=0.02)


@pytest.mark.parametrize(
    "bad",
    [
        {"graph_frame_distance_m": 0.0},
        {"graph_frame_distance_m": float("nan")},
        {"graph_frame_angle_rad": 0.0},
        {"graph_frame_max_gap": 0},
        {"graph_frame_min_landmarks": -1},
    ],
)
def test_graph_frame_settings_are_validated(bad: dict[str, float]) -> None:
    with pytest.raises(ValueError, match="graph_frame"):
        SlamConfig(**bad)  # type: ignore[arg-type]
