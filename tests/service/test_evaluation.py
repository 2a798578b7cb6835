"""Trajectories, TUM files, ATE and dead reckoning."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from graph.angles import wrap_angles
from graph.types import FrameInput, Odometry, Pose2D
from service.offline.evaluation import (
    Trajectory,
    align_se2,
    associate,
    ate_rmse,
    dead_reckoning,
    fit_landmarks,
    interpolate,
    read_tum,
    write_tum,
)


def _rot(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def _random_traj(rng: np.random.Generator, n: int = 50) -> Trajectory:
    stamps = np.cumsum(rng.uniform(0.05, 0.2, n)) + 1000.0
    xy = np.cumsum(rng.normal(0.0, 0.3, (n, 2)), axis=0)
    return Trajectory(stamps, xy, rng.uniform(-4.0, 4.0, n))


def test_trajectory_validates_and_wraps() -> None:
    traj = Trajectory(np.array([0.0, 1.0]), np.zeros((2, 2)), np.array([-math.pi, 3 * math.pi]))
    np.testing.assert_allclose(traj.theta, [math.pi, math.pi])
    with pytest.raises(ValueError, match="length"):
        Trajectory(np.zeros(3), np.zeros((2, 2)), np.zeros(2))
    with pytest.raises(ValueError, match="non-decreasing"):
        Trajectory(np.array([1.0, 0.0]), np.zeros((2, 2)), np.zeros(2))


def test_convention_tum_quaternion_is_rotation_about_z(tmp_path: Path) -> None:
    traj = Trajectory(np.array([1.5]), np.array([[2.0, -3.0]]), np.array([math.pi / 2]))
    path = tmp_path / "t.tum"
    write_tum(path, traj)
    rows = [line.split() for line in path.read_text().splitlines() if not line.startswith("#")]
    half = f"{math.sqrt(0.5):.6f}"  # sin(pi/4) = cos(pi/4)
    assert rows == [["1.500000", "2.000000", "-3.000000", *(["0.000000"] * 3), half, half]]


def test_tum_round_trip(tmp_path: Path) -> None:
    traj = _random_traj(np.random.default_rng(0))
    path = tmp_path / "t.tum"
    write_tum(path, traj)
    path.write_text("# a comment\n" + path.read_text())
    back = read_tum(path)
    np.testing.assert_allclose(back.stamps, traj.stamps, atol=1e-6)
    np.testing.assert_allclose(back.xy, traj.xy, atol=1e-6)
    np.testing.assert_allclose(wrap_angles(back.theta - traj.theta), 0.0, atol=1e-5)


def test_read_tum_takes_yaw_from_a_full_quaternion(tmp_path: Path) -> None:
    # yaw 0.3 then roll 0.2: q = q_z(0.3) * q_x(0.2); yaw read back must be 0.3
    cz, sz, cx, sx = math.cos(0.15), math.sin(0.15), math.cos(0.1), math.sin(0.1)
    qw, qx, qy, qz = cz * cx, cz * sx, sz * sx, sz * cx
    path = tmp_path / "t.tum"
    path.write_text(f"0 1 2 3 {qx} {qy} {qz} {qw}\n")
    assert read_tum(path).theta[0] == pytest.approx(0.3)


def test_interpolate_is_linear_and_takes_the_short_arc() -> None:
    gt = Trajectory(
        np.array([0.0, 1.0, 2.0, 10.0]),
        np.array([[0.0, 0.0], [1.0, 2.0], [3.0, 2.0], [3.0, 10.0]]),
        np.array([3.0, -3.0, 0.0, 0.0]),
    )
    valid, at = interpolate(gt, [0.5, 1.0, -1.0, 2.0, 5.0, 11.0], max_gap_s=1.0)
    assert valid.tolist() == [True, True, False, True, False, False]
    np.testing.assert_allclose(at.xy, [[0.5, 1.0], [1.0, 2.0], [3.0, 2.0]])
    # 3 -> -3 rad is a step of 2 pi - 6 ~ +0.28 rad across +pi, not -6 rad
    assert wrap_angles(at.theta[0] - (3.0 + 0.5 * (2 * math.pi - 6.0))) == pytest.approx(0.0)


def test_ate_is_zero_for_the_truth_and_drops_stamps_outside() -> None:
    gt = _random_traj(np.random.default_rng(1))
    assert ate_rmse(gt, gt) == pytest.approx(0.0, abs=1e-12)
    est = Trajectory(
        np.concatenate([[gt.stamps[0] - 5.0], gt.stamps, [gt.stamps[-1] + 5.0]]),
        np.vstack([[100.0, 100.0], gt.xy, [100.0, 100.0]]),
        np.zeros(len(gt) + 2),
    )
    assert ate_rmse(est, gt) == pytest.approx(0.0, abs=1e-12)


def test_ate_of_a_constant_offset_and_gap_handling() -> None:
    gt = Trajectory(
        np.array([0.0, 1.0, 2.0, 5.0, 6.0]),
        np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [5.0, 0.0], [6.0, 0.0]]),
        np.zeros(5),
    )
    stamps = np.array([0.5, 1.5, 3.0, 5.5])  # 3.0 lies in a 3 s gap of gt: dropped
    est = Trajectory(stamps, np.column_stack([stamps, np.full(4, 0.3)]), np.zeros(4))
    kept, _, _ = associate(est, gt)
    assert kept.tolist() == [0.5, 1.5, 5.5]
    assert ate_rmse(est, gt) == pytest.approx(0.3)
    assert ate_rmse(est, gt, align=True) == pytest.approx(0.0, abs=1e-12)


def test_ate_needs_two_overlapping_stamps() -> None:
    gt = _random_traj(np.random.default_rng(2))
    est = Trajectory(np.array([gt.stamps[3], gt.stamps[-1] + 1.0]), np.zeros((2, 2)), np.zeros(2))
    with pytest.raises(ValueError, match="at least 2"):
        ate_rmse(est, gt)


def test_alignment_recovers_a_rigid_motion() -> None:
    rng = np.random.default_rng(3)
    gt = _random_traj(rng)
    rot, trans = _rot(2.5), np.array([4.0, -7.0])
    moved = Trajectory(gt.stamps, gt.xy @ rot.T + trans, gt.theta)
    assert ate_rmse(moved, gt) > 1.0
    assert ate_rmse(moved, gt, align=True) == pytest.approx(0.0, abs=1e-9)
    r_est, t_est = align_se2(moved.xy, gt.xy)
    np.testing.assert_allclose(r_est, rot.T, atol=1e-9)
    np.testing.assert_allclose(moved.xy @ r_est.T + t_est, gt.xy, atol=1e-9)


def test_map_fit_splits_frame_shape_and_scale() -> None:
    rng = np.random.default_rng(6)
    surveyed = {str(i): rng.uniform(-4.0, 4.0, 2) for i in range(12)}
    rot, trans = _rot(0.3), np.array([0.5, -0.2])
    # the map 5 % smaller than the arena, turned and shifted
    estimated = {k: 0.95 * (v @ rot.T) + trans for k, v in surveyed.items()}
    fit = fit_landmarks(estimated, surveyed)
    assert fit.rotation_rad == pytest.approx(-0.3, abs=1e-9)
    assert fit.scale == pytest.approx(1 / 0.95, rel=1e-9)
    assert fit.rmse_aligned_m > 0.05  # a rigid fit cannot take the scale out
    same = fit_landmarks({k: v @ rot.T + trans for k, v in surveyed.items()}, surveyed)
    assert same.scale == pytest.approx(1.0, abs=1e-9)
    assert same.rmse_aligned_m == pytest.approx(0.0, abs=1e-9)


def test_alignment_never_reflects() -> None:
    rng = np.random.default_rng(4)
    src = rng.normal(size=(30, 2))
    dst = src * np.array([1.0, -1.0])  # a mirror image: the best rotation is no reflection
    rot, _ = align_se2(src, dst)
    assert np.linalg.det(rot) == pytest.approx(1.0)


def test_aligned_ate_is_never_larger() -> None:
    rng = np.random.default_rng(5)
    for _ in range(20):
        gt = _random_traj(rng)
        est = Trajectory(gt.stamps, gt.xy + rng.normal(0, 0.5, gt.xy.shape), gt.theta)
        assert ate_rmse(est, gt, align=True) <= ate_rmse(est, gt) + 1e-12


def _frame(
    seq: int, odo: tuple[float, float, float] | None, pose: Pose2D | None = None
) -> FrameInput:
    return FrameInput(
        robot="r1",
        seq=seq,
        stamp=float(seq),
        odometry=None if odo is None else Odometry(*odo),
        initial_pose=pose,
    )


def test_convention_odometry_is_in_the_previous_robot_frame() -> None:
    # Facing +y, one metre forward then turn left: ends at (1, 1) facing -x.
    frames = [
        _frame(0, None, Pose2D(1.0, 0.0, math.pi / 2)),
        _frame(1, (1.0, 0.0, math.pi / 2)),
        _frame(2, (0.0, 1.0, 0.0)),  # one metre to the left = -x in the map
    ]
    traj = dead_reckoning(frames)
    np.testing.assert_allclose(traj.xy, [[1.0, 0.0], [1.0, 1.0], [1.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(traj.theta, [math.pi / 2, math.pi, math.pi])


def test_dead_reckoning_square_closes() -> None:
    frames = [_frame(0, None, Pose2D(0.0, 0.0, 0.0))]
    frames += [_frame(i, (1.0, 0.0, math.pi / 2)) for i in range(1, 9)]
    traj = dead_reckoning(frames)
    np.testing.assert_allclose(traj.xy[8], [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(traj.xy[:5], [[0, 0], [1, 0], [1, 1], [0, 1], [0, 0]], atol=1e-12)


def test_dead_reckoning_refuses_incomplete_input() -> None:
    with pytest.raises(ValueError, match="initial_pose"):
        dead_reckoning([_frame(0, (0.0, 0.0, 0.0))])
    with pytest.raises(ValueError, match="no odometry"):
        dead_reckoning([_frame(0, None, Pose2D(0, 0, 0)), _frame(1, None)])
