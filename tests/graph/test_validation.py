"""Bad frames raise a typed error naming the field, and leave the map exactly as it was."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from graph.config import SlamConfig
from graph.errors import InvalidFrame, OutOfOrderFrame, UnknownRobot
from graph.slam import BearingSlam
from graph.types import BearingObservation, FrameInput, Odometry, Pose2D
from tests.graph._world import circle_frames


def _snapshot(slam: BearingSlam) -> tuple:
    est = slam.graph.estimate()
    values = sorted(
        (
            int(k),
            tuple(np.ravel(est.atPose2(k).matrix()))
            if slam.graph.estimate().exists(k) and chr(k >> 56) == "x"
            else tuple(np.ravel(est.atPoint2(k))),
        )
        for k in est.keys()
    )
    return (
        slam.frame_count,
        slam.graph.num_factors,
        slam.graph.num_variables,
        values,
        sorted((i, r.count, tuple(r.observed_from)) for i, r in slam.landmarks.items()),
        slam.candidate_count,
        len(slam.removals),
        {k: v.tobytes() for k, v in slam.trajectory().items()},
    )


@pytest.fixture(scope="module")
def warm() -> tuple[BearingSlam, FrameInput]:
    frames, _, _ = circle_frames(60, seed=1, n_landmarks=20)
    slam = BearingSlam(SlamConfig(landmark_cap=6, pose_window=30), rng=np.random.default_rng(0))
    for f in frames[:-1]:
        slam.process(f, with_covariance=False)
    return slam, frames[-1]


def _obs(frame: FrameInput, **changes: object) -> FrameInput:
    first = replace(frame.observations[0], **changes)  # type: ignore[arg-type]
    return replace(frame, observations=(first, *frame.observations[1:]))


BAD = {
    "nan bearing": (
        lambda f: _obs(f, bearing_rad=math.nan),
        InvalidFrame,
        "observations[0].bearing",
    ),
    "inf bearing": (
        lambda f: _obs(f, bearing_rad=math.inf),
        InvalidFrame,
        "observations[0].bearing",
    ),
    "bearing -pi": (
        lambda f: _obs(f, bearing_rad=-math.pi),
        InvalidFrame,
        "observations[0].bearing",
    ),
    "bearing > pi": (lambda f: _obs(f, bearing_rad=3.5), InvalidFrame, "observations[0].bearing"),
    "zero sigma": (lambda f: _obs(f, sigma_rad=0.0), InvalidFrame, "observations[0].sigma"),
    "empty label": (lambda f: _obs(f, label=""), InvalidFrame, "observations[0].label"),
    "duplicate label": (
        lambda f: replace(f, observations=(f.observations[0], f.observations[0])),
        InvalidFrame,
        "observations[1].label",
    ),
    "nan odometry": (
        lambda f: replace(f, odometry=Odometry(math.nan, 0.0, 0.0)),
        InvalidFrame,
        "odometry.dx",
    ),
    "negative odometry sigma": (
        lambda f: replace(f, odometry=Odometry(0.1, 0.0, 0.0, sigma_x=-1.0)),
        InvalidFrame,
        "odometry.sigma_x",
    ),
    "missing odometry": (lambda f: replace(f, odometry=None), InvalidFrame, "odometry"),
    "stale seq": (lambda f: replace(f, seq=3), OutOfOrderFrame, "seq"),
    "repeated seq": (lambda f: replace(f, seq=f.seq - 1), OutOfOrderFrame, "seq"),
    "stamp backwards": (lambda f: replace(f, stamp=0.5), OutOfOrderFrame, "stamp"),
    "nan stamp": (lambda f: replace(f, stamp=math.nan), InvalidFrame, "stamp"),
    "negative seq": (lambda f: replace(f, seq=-1), InvalidFrame, "seq"),
    "empty robot": (lambda f: replace(f, robot=""), InvalidFrame, "robot"),
    "unknown robot without pose": (lambda f: replace(f, robot="r9"), UnknownRobot, "initial_pose"),
    "new robot with nan pose": (
        lambda f: replace(f, robot="r9", initial_pose=Pose2D(0.0, math.nan, 0.0)),
        InvalidFrame,
        "initial_pose.y",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_frame_is_refused_and_map_unchanged(
    case: str, warm: tuple[BearingSlam, FrameInput]
) -> None:
    slam, good = warm
    make, error, field = BAD[case]
    before = _snapshot(slam)
    with pytest.raises(error) as info:
        slam.process(make(good))
    assert info.value.field == field
    assert info.value.detail
    assert _snapshot(slam) == before


def test_good_frame_after_refusals_is_accepted(warm: tuple[BearingSlam, FrameInput]) -> None:
    slam, good = warm
    n = slam.frame_count
    out = slam.process(good)
    assert slam.frame_count == n + 1
    assert out.covariance is not None and out.covariance.shape == (3, 3)
    assert np.all(np.linalg.eigvalsh(out.covariance) > 0)


def test_convention_bearing_counter_clockwise() -> None:
    """A landmark seen at +pi/2 from a robot facing +x lies at +y (REP-103)."""
    slam = BearingSlam(SlamConfig(landmark_cap=None), rng=np.random.default_rng(0))
    target = np.array([1.0, 3.0])
    for k in range(8):
        x = 0.25 * k
        bearing = math.atan2(target[1], target[0] - x)
        obs = (BearingObservation(bearing, "a", 0.001),)
        if k == 0:
            slam.process(FrameInput("r", 0, 0.0, None, Pose2D(0.0, 0.0, 0.0), obs))
        else:
            slam.process(FrameInput("r", k, float(k), Odometry(0.25, 0.0, 0.0), None, obs))
    (lid,) = slam.landmarks
    np.testing.assert_allclose(slam.landmark_position(lid), target, atol=0.02)
