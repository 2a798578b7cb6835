"""MRCLAM as frames: odometry integration, frame construction, and smoke runs on dataset 6."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from graph.angles import wrap_angles
from graph.types import FrameInput
from service.offline.datasets.mrclam import (
    ROBOT_SUBJECTS,
    MrclamRobot,
    dead_reckoning,
    default_mrclam_dir,
    integrate_unicycle,
    load_mrclam,
    measurement_rate_hz,
    mrclam_frames,
    relative_motion,
)
from service.offline.evaluation import Trajectory, ate_rmse, interpolate

V, W = 0.4, 0.25  # m/s, rad/s
P0 = np.array([1.0, 2.0, 0.5])  # pose at the first odometry sample, t = 100 s


def _circle(t: np.ndarray, v: float = V, w: float = W, p0: np.ndarray = P0) -> np.ndarray:
    """(N, 3) analytic unicycle poses at constant (v, w) from p0 at t = 100."""
    tau = t - 100.0
    local = np.column_stack([v / w * np.sin(w * tau), v / w * (1.0 - np.cos(w * tau))])
    c, s = math.cos(p0[2]), math.sin(p0[2])
    xy = p0[:2] + local @ np.array([[c, s], [-s, c]])
    return np.column_stack([xy, p0[2] + w * tau])


def _odometry(rng: np.random.Generator, t0: float, t1: float, v: float, w: float) -> np.ndarray:
    t = np.sort(np.concatenate([[t0], rng.uniform(t0, t1, int((t1 - t0) * 67))]))
    return np.column_stack([t, np.full_like(t, v), np.full_like(t, w)])


def test_integration_on_a_circle_is_exact() -> None:
    odo = _odometry(np.random.default_rng(0), 100.0, 160.0, V, W)
    stamps = np.random.default_rng(1).uniform(100.0, 170.0, 200)  # past the last sample too
    poses = integrate_unicycle(odo, stamps)
    origin = np.zeros(3)
    np.testing.assert_allclose(poses, _circle(stamps, p0=origin), atol=1e-9)


@pytest.mark.parametrize("w", [0.0, 1e-13, -1e-9])
def test_integration_straight_line_limit(w: float) -> None:
    odo = np.array([[0.0, 0.5, w], [1.0, 0.5, w], [3.0, 0.5, w]])
    poses = integrate_unicycle(odo, np.array([0.0, 0.5, 2.0, 4.0]))
    np.testing.assert_allclose(poses[:, 0], [0.0, 0.25, 1.0, 2.0], atol=1e-9)
    np.testing.assert_allclose(poses[:, 1:], 0.0, atol=1e-8)


def test_integration_matches_fine_euler_for_varying_odometry() -> None:
    rng = np.random.default_rng(2)
    odo = np.column_stack(
        [np.arange(0.0, 5.0, 0.015), rng.uniform(0.0, 0.5, 334), rng.uniform(-2.0, 2.0, 334)]
    )
    query = np.array([0.0, 1.234, 4.99])
    fine_t = np.linspace(0.0, 4.99, 499_001)
    k = np.searchsorted(odo[:, 0], fine_t[:-1], side="right") - 1
    dt = np.diff(fine_t)
    theta = np.concatenate([[0.0], np.cumsum(odo[k, 2] * dt)])
    mid = theta[:-1] + 0.5 * odo[k, 2] * dt  # midpoint heading of each fine step
    step = (odo[k, 1] * dt)[:, None] * np.column_stack([np.cos(mid), np.sin(mid)])
    xy = np.vstack([[0.0, 0.0], np.cumsum(step, axis=0)])
    idx = np.searchsorted(fine_t, query)
    expected = np.column_stack([xy[idx], theta[idx]])
    np.testing.assert_allclose(integrate_unicycle(odo, query), expected, atol=1e-6)


def test_convention_relative_motion_in_previous_frame() -> None:
    poses = np.array([[0.0, 0.0, math.pi / 2], [0.0, 1.0, -3.0], [0.0, 1.0, 3.0]])
    motion = relative_motion(poses)
    np.testing.assert_allclose(motion[0], [1.0, 0.0, wrap_angles(-3.0 - math.pi / 2)], atol=1e-12)
    np.testing.assert_allclose(motion[1], [0.0, 0.0, 6.0 - 2 * math.pi], atol=1e-12)


def _synthetic() -> MrclamRobot:
    """A robot driving a circle; barcodes: 5 = robot 1, 14 = robot 2, 63 = 6, 81 = 7, 7 = 8."""
    gt_t = np.arange(100.5, 150.5 + 1e-9, 0.01)
    meas = np.array(
        [
            [100.2, 63, 1.0, 0.1],  # before ground truth: no frame
            [101.0, 63, 1.0, 0.1],  # first frame
            [101.0, 14, 1.0, 0.2],  # another robot: dropped
            [101.0005, 81, 1.0, 0.3],  # within group_tol: same frame
            [101.0005, 63, 1.0, 0.4],  # repeated label in a frame: dropped
            [103.5, 7, 1.0, -0.5],  # 2.5 s later: two odometry-only frames before it
            [104.0, 14, 1.0, 0.2],  # only a robot: no frame
            [104.2, 99, 1.0, 0.2],  # unknown barcode: no frame
            [149.0, 81, 1.0, 3.5],  # a bearing beyond pi: wrapped
            [151.0, 63, 1.0, 0.1],  # after ground truth: no frame
        ]
    )
    return MrclamRobot(
        robot=3,
        odometry=_odometry(np.random.default_rng(3), 100.0, 160.0, V, W),
        measurements=meas,
        groundtruth=np.column_stack([gt_t, _circle(gt_t)]),
        barcodes=np.array([[1, 5], [2, 14], [6, 63], [7, 81], [8, 7]]),
    )


def test_frames_from_synthetic_tables() -> None:
    data = _synthetic()
    frames, truth = mrclam_frames(data, bearing_sigma_rad=0.02)
    stamps = [f.stamp for f in frames]
    assert stamps[:4] == pytest.approx([101.0, 101.0 + 2.5 / 3, 101.0 + 5.0 / 3, 103.5])
    assert all(0 < b - a <= 1.0 + 1e-9 for a, b in itertools.pairwise(stamps))
    assert stamps[-1] == pytest.approx(150.0)  # a tail frame every second to the end of gt
    assert [f.seq for f in frames] == list(range(len(frames)))
    assert {f.robot for f in frames} == {"r3"}

    assert [o.label for o in frames[0].observations] == ["6", "7"]
    assert [o.bearing_rad for o in frames[0].observations] == pytest.approx([0.1, 0.3])
    assert frames[0].observations[0].sigma_rad == 0.02
    assert frames[1].observations == () and frames[2].observations == ()
    assert [o.label for o in frames[3].observations] == ["8"]
    (late,) = [f for f in frames if f.stamp == 149.0]
    assert late.observations[0].bearing_rad == pytest.approx(3.5 - 2 * math.pi)
    labelled = [f for f in frames if f.observations]
    assert len(labelled) == 3

    assert frames[0].odometry is None and frames[0].initial_pose is not None
    assert all(f.odometry is not None and f.initial_pose is None for f in frames[1:])
    expected = _circle(np.array(stamps))
    pose0 = frames[0].initial_pose
    np.testing.assert_allclose([pose0.x, pose0.y, pose0.theta], expected[0], atol=1e-5)

    # odometry across frames composes back to the circle
    dr = dead_reckoning(frames)
    np.testing.assert_allclose(dr.xy, expected[:, :2], atol=1e-5)
    np.testing.assert_allclose(wrap_angles(dr.theta - expected[:, 2]), 0.0, atol=1e-5)
    assert truth.stamps[0] <= stamps[0] and truth.stamps[-1] == pytest.approx(150.5)


# --------------------------------------------------------------------------- real data

DATA = default_mrclam_dir()
needs_data = pytest.mark.skipif(
    not (DATA / "Barcodes.dat.gz").is_file() and not (DATA / "Barcodes.dat").is_file(),
    reason=f"MRCLAM dataset 6 not found in {DATA} (set COVSLAM_DATA to the data directory)",
)


@pytest.fixture(scope="module")
def mrclam() -> dict[int, tuple[MrclamRobot, list[FrameInput], Trajectory]]:
    out = {}
    for robot in sorted(ROBOT_SUBJECTS):
        data = load_mrclam(DATA, robot)
        frames, truth = mrclam_frames(data)
        out[robot] = (data, frames, truth)
    return out


@needs_data
@pytest.mark.parametrize("robot", [1, 2, 3, 4, 5])
def test_dataset6_frames_are_plausible(mrclam: dict, robot: int) -> None:
    data, frames, truth = mrclam[robot]
    labelled = [f for f in frames if f.observations]
    span = frames[-1].stamp - frames[0].stamp
    print(
        f"robot {robot}: {len(frames)} frames, {len(labelled)} with bearings, "
        f"{measurement_rate_hz(frames):.2f} bearings/s over {span:.0f} s"
    )
    assert 700.0 < span < 1000.0
    assert 500 < len(labelled) <= len(frames) < 5000
    assert [f.seq for f in frames] == list(range(len(frames)))
    assert np.all(np.diff([f.stamp for f in frames]) > 0)
    assert np.max(np.diff([f.stamp for f in frames])) <= 1.0 + 1e-6
    labels = {o.label for f in frames for o in f.observations}
    assert labels <= {str(s) for s in range(6, 21)}
    assert not labels & {str(s) for s in ROBOT_SUBJECTS}
    assert frames[0].stamp >= max(data.odometry[0, 0], truth.stamps[0])
    assert frames[-1].stamp <= truth.stamps[-1]


@needs_data
@pytest.mark.parametrize("robot", [1, 2, 3, 4, 5])
def test_convention_dataset6_bearings_match_ground_truth(mrclam: dict, robot: int) -> None:
    data, frames, truth = mrclam[robot]
    landmarks = {str(int(s)): (x, y) for s, x, y in data.landmarks}
    stamps = np.array([f.stamp for f in frames for _ in f.observations])
    bearings = np.array([o.bearing_rad for f in frames for o in f.observations])
    where = np.array([landmarks[o.label] for f in frames for o in f.observations])
    valid, at = interpolate(truth, stamps, max_gap_s=0.1)
    rel = where[valid] - at.xy
    predicted = np.arctan2(rel[:, 1], rel[:, 0]) - at.theta
    error = np.abs(wrap_angles(bearings[valid] - predicted))
    assert np.median(error) < np.deg2rad(1.5)
    assert np.all(np.abs(bearings) <= math.pi)


@needs_data
@pytest.mark.parametrize("robot", [1, 2, 3, 4, 5])
def test_dataset6_dead_reckoning(mrclam: dict, robot: int) -> None:
    _, frames, truth = mrclam[robot]
    dr = dead_reckoning(frames)
    early = dr.stamps <= dr.stamps[0] + 10.0
    valid, at = interpolate(truth, dr.stamps[early])
    assert np.max(np.linalg.norm(dr.xy[early][valid] - at.xy, axis=1)) < 0.5
    ate = ate_rmse(dr, truth)
    aligned = ate_rmse(dr, truth, align=True)
    print(f"robot {robot}: dead-reckoning ATE {ate:.2f} m, aligned {aligned:.2f} m")
    assert 0.3 < ate < 20.0  # of order metres: the odometry is poor
