"""The upkeep after a frame (SlamConfig.upkeep "after_frame"): the budget's removals,
a second window exit and keyframe thinning leave the frame, and the map is the same
however the upkeeps were timed."""

from __future__ import annotations

import dataclasses
import pickle

import gtsam
import numpy as np
import pytest

from graph.config import SlamConfig
from graph.factors import pose_key
from graph.slam import BearingSlam, RemovalRecord
from graph.snapshot import capture, restore
from graph.trajectory import PoseRow
from tests.graph._world import circle_frames

CAPPED = SlamConfig(landmark_cap=10, pose_window=30, upkeep="after_frame")


class _Sinks:
    def __init__(self) -> None:
        self.removals: list[RemovalRecord] = []
        self.rows: list[PoseRow] = []

    def map(self, config: SlamConfig, seed: int = 0) -> BearingSlam:
        return BearingSlam(
            config,
            rng=np.random.default_rng(seed),
            removal_sink=self.removals.append,
            trajectory_sink=self.rows.extend,
        )


def _trajectory(slam: BearingSlam) -> np.ndarray:
    return slam.trajectory("r1")["r1"]


@pytest.mark.parametrize("upkeep", ["budget_after_frame", "after_frame"])
def test_the_map_does_not_depend_on_when_the_upkeeps_ran(upkeep: str) -> None:
    """Upkeep after every frame (the service), or left for the next frame to run first (a
    plain loop of `process`): the same removals, landmarks and trajectory, bit for bit."""
    frames, _, _ = circle_frames(140, seed=3)
    eager_sinks, lazy_sinks = _Sinks(), _Sinks()
    config = dataclasses.replace(CAPPED, upkeep=upkeep)
    eager, lazy = eager_sinks.map(config), lazy_sinks.map(config)
    for f in frames:
        a = eager.process(f, with_covariance=False)
        eager.upkeep()
        b = lazy.process(f, with_covariance=False)
        assert a.marginalised == b.marginalised
        assert (a.pose.x, a.pose.y, a.pose.theta) == (b.pose.x, b.pose.y, b.pose.theta)
    eager.settle()
    lazy.settle()
    assert eager.removal_count > 5, "the run must exercise the budget"
    assert eager_sinks.removals == lazy_sinks.removals
    assert eager_sinks.rows == lazy_sinks.rows
    assert sorted(eager.landmarks) == sorted(lazy.landmarks)
    np.testing.assert_array_equal(_trajectory(eager), _trajectory(lazy))


def test_a_frame_reports_the_removals_made_after_the_frame_before() -> None:
    frames, _, _ = circle_frames(140, seed=3)
    sinks = _Sinks()
    slam = sinks.map(CAPPED)
    cap = CAPPED.landmark_cap
    assert cap is not None
    reported: list[int] = []
    for f in frames:
        outcome = slam.process(f, with_covariance=False)
        # Handed to the sink with the outcome that names them, made after an earlier frame.
        assert [r.landmark_id for r in sinks.removals[len(reported) :]] == list(
            outcome.marginalised
        )
        assert all(r.frame < outcome.frame_index for r in sinks.removals[len(reported) :])
        reported.extend(outcome.marginalised)
        before = len(slam.landmarks)
        slam.upkeep()
        assert not slam.upkeep_pending
        assert len(slam.landmarks) <= cap
        if before > cap:
            assert len(slam.landmarks) <= cap - CAPPED.removal_margin
    assert len(reported) > 5
    slam.settle()
    assert len(sinks.removals) == slam.removal_count


def test_a_snapshot_keeps_a_pending_upkeep() -> None:
    """A snapshot taken between a frame and its upkeep (a worker's idle snapshot, a
    shutdown) restores with the upkeep still to run and the removals still to report."""
    frames, _, _ = circle_frames(140, seed=3)
    original = BearingSlam(CAPPED, rng=np.random.default_rng(0))
    for f in frames[:100]:
        original.process(f, with_covariance=False)
    assert original.upkeep_pending
    restored = restore(capture(original))
    assert restored.upkeep_pending
    for f in frames[100:]:
        a = original.process(f, with_covariance=False)
        b = restored.process(f, with_covariance=False)
        # The same removals (a restored map's floats are not bit-exact: two landmarks
        # the policy ranks alike may swap places in a frame's list).
        assert sorted(a.marginalised) == sorted(b.marginalised)
        assert abs(a.pose.x - b.pose.x) < 0.02 and abs(a.pose.y - b.pose.y) < 0.02
    assert original.removal_count == restored.removal_count


def test_relinearisation_after_the_frame_leaves_the_frame_linear() -> None:
    """With upkeep "after_frame" the frame's own update keeps every linearisation point
    it found; the upkeep moves them."""
    frames, _, _ = circle_frames(60, seed=4)
    slam = BearingSlam(CAPPED, rng=np.random.default_rng(0))
    moved_in_upkeep = 0
    for f in frames:
        keys = [pose_key(0, k) for k in range(f.seq) if pose_key(0, k) in slam.graph]
        before = [slam.graph.linearization_point().atPose2(k) for k in keys]
        slam.process(f, with_covariance=False)
        during = [slam.graph.linearization_point().atPose2(k) for k in keys]
        for a, b in zip(before, during, strict=True):
            assert a.equals(b, 0.0)
        slam.upkeep()
        after = [slam.graph.linearization_point().atPose2(k) for k in keys]
        moved_in_upkeep += sum(not a.equals(b, 0.0) for a, b in zip(during, after, strict=True))
    assert moved_in_upkeep > 0


def test_an_unknown_upkeep_is_refused() -> None:
    with pytest.raises(ValueError, match="upkeep"):
        SlamConfig(upkeep="later")  # type: ignore[arg-type]


def test_a_snapshot_reads_its_config_by_field_name() -> None:
    """A config field added later gets its default, one removed later is ignored: the
    other fields keep their values (a positional pickle would shift them)."""
    frames, _, _ = circle_frames(30, seed=5)
    slam = BearingSlam(SlamConfig(landmark_cap=7, pose_window=20), rng=np.random.default_rng(0))
    for f in frames:
        slam.process(f, with_covariance=False)
    state = pickle.loads(capture(slam))
    del state["slam"]["config"]["upkeep"]
    state["slam"]["config"]["a_field_no_longer_there"] = 1
    restored = restore(pickle.dumps(state))
    assert restored.config == SlamConfig(landmark_cap=7, pose_window=20)
    assert isinstance(restored.graph.pose(pose_key(0, 29)), gtsam.Pose2)
