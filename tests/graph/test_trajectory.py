"""graph.trajectory: final rows leave the estimator through its sink, nothing changes."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from graph.config import SlamConfig
from graph.slam import BearingSlam
from graph.snapshot import capture, restore
from graph.trajectory import PoseRow
from graph.types import FrameInput
from tests.graph._world import circle_frames

# Window exits, keyframes, keyframe thinning and landmark removals, all within 400 frames.
BOUNDED = SlamConfig(landmark_cap=8, pose_window=15, window_observations=None, max_keyframes=6)


def _two_robots(n: int, seed: int) -> list[FrameInput]:
    """r1 all along; r2 (the same circle, its own chain) joins at r1's frame 60."""
    r1, _, _ = circle_frames(n, seed=seed, n_landmarks=30)
    r2, _, _ = circle_frames(n - 60, seed=seed, n_landmarks=30, robot="r2")
    out = list(r1[:60])
    for a, b in zip(r1[60:], r2, strict=False):
        out += [a, b]
    return out


class _Sink:
    def __init__(self) -> None:
        self.rows: list[PoseRow] = []
        self.calls = 0

    def __call__(self, rows: list[PoseRow]) -> None:
        self.calls += 1
        self.rows.extend(rows)

    def table(self, robot: str) -> np.ndarray:
        mine = [(r.seq, r.stamp, r.x, r.y, r.theta) for r in self.rows if r.robot == robot]
        return np.array(mine, dtype=np.float64).reshape(-1, 5)


def _merged(slam: BearingSlam, sink: _Sink, robot: str) -> np.ndarray:
    rows = np.concatenate([sink.table(robot), slam.trajectory(robot)[robot]])
    return rows[np.argsort(rows[:, 0], kind="stable")]


@pytest.mark.parametrize(
    "config",
    [
        BOUNDED,
        SlamConfig(
            landmark_cap=8,
            pose_window=15,
            window_observations=None,
            max_keyframes=6,
            graph_frame_distance_m=0.3,
        ),
    ],
    ids=["every-frame", "tracked-frames"],
)
def test_sunk_and_held_rows_are_bit_identical_to_keeping_every_row(config: SlamConfig) -> None:
    frames = _two_robots(400, seed=6)
    kept = BearingSlam(config, rng=np.random.default_rng(1))
    sink = _Sink()
    sunk = BearingSlam(config, rng=np.random.default_rng(1), trajectory_sink=sink)
    for f in frames:
        kept.process(f, with_covariance=False)
        sunk.process(f, with_covariance=False)
    assert kept.removal_count > 0, "the run must remove landmarks"
    reference = kept.trajectory()
    for robot in ("r1", "r2"):
        merged = _merged(sunk, sink, robot)
        assert merged.tobytes() == reference[robot].tobytes(), robot
    # Every frame is in exactly one place: the sink or the estimator.
    assert len(sink.rows) + sunk.held_trajectory_rows == len(frames)
    assert len({(r.robot, r.seq) for r in sink.rows}) == len(sink.rows)
    assert len(sink.rows) > len(frames) // 2
    assert sunk._trajectory.kept_count == 0 and kept._trajectory.kept_count == len(sink.rows)


def test_held_rows_stay_bounded_while_the_frames_grow() -> None:
    frames, _, _ = circle_frames(1200, seed=7, n_landmarks=30)
    sink = _Sink()
    slam = BearingSlam(BOUNDED, rng=np.random.default_rng(2), trajectory_sink=sink)
    held = []
    for f in frames:
        slam.process(f, with_covariance=False)
        held.append(slam.held_trajectory_rows)
    # Bounded by the window, the keyframes and the frames that follow them, not by the
    # run's length: the second half holds about what the first did at its most (a
    # keyframe's followers vary by a few frames), not twice as much.
    assert max(held[600:]) <= 1.25 * max(held[:600])
    assert held[-1] < 200 < len(frames)
    # The estimator's state (what a snapshot pickles) does not carry the sunk rows: a
    # tenth of what the run's rows take kept (44 bytes each) is more than it holds.
    assert len(sink.rows) == len(frames) - held[-1]
    assert len(pickle.dumps(slam._trajectory)) < 44 * len(frames) / 10


def test_restore_with_a_sink_goes_on_sinking_only_new_final_rows() -> None:
    frames, _, _ = circle_frames(300, seed=8, n_landmarks=30)
    reference = BearingSlam(BOUNDED, rng=np.random.default_rng(3))
    for f in frames:
        reference.process(f, with_covariance=False)
    before = _Sink()
    original = BearingSlam(BOUNDED, rng=np.random.default_rng(3), trajectory_sink=before)
    for f in frames[:150]:
        original.process(f, with_covariance=False)
    after = _Sink()
    restored = restore(capture(original), trajectory_sink=after)
    assert restored.held_trajectory_rows == original.held_trajectory_rows
    for f in frames[150:]:
        restored.process(f, with_covariance=False)
    seqs = [r.seq for r in before.rows] + [r.seq for r in after.rows]
    assert len(seqs) == len(set(seqs)), "a row was finalised twice"
    combined = _Sink()
    combined.rows = before.rows + after.rows
    merged = _merged(restored, combined, "r1")
    truth = reference.trajectory("r1")["r1"]
    np.testing.assert_array_equal(merged[:, :2], truth[:, :2])
    # The restore rebuilds iSAM2 in one step (see test_snapshot): close, not identical.
    np.testing.assert_allclose(merged[:, 2:], truth[:, 2:], atol=0.05)
