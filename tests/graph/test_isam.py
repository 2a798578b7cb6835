"""IncrementalGraph's factor index stays as small as what it indexes (graph.isam)."""

from __future__ import annotations

import math
import sys

import gtsam
import numpy as np

from graph.config import SlamConfig
from graph.factors import (
    bearing_factor,
    landmark_key,
    landmark_prior_factor,
    odometry_factor,
    pose_key,
    pose_prior_factor,
)
from graph.isam import IncrementalGraph
from graph.slam import BearingSlam
from graph.types import Odometry, Pose2D
from tests.graph._world import circle_frames

SIGMA = 0.02


def _table_bytes_ok(graph: IncrementalGraph) -> list[tuple[int, int, int]]:
    """Index sets over 1 KiB with more than 16 table slots (256 bytes) per element:
    (key, elements, bytes)."""
    empty = sys.getsizeof(set())
    return [
        (key, len(s), sys.getsizeof(s))
        for key, s in graph._key_factors.items()
        if sys.getsizeof(s) > max(1024, 256 * len(s) + empty)
    ]


def test_a_landmark_that_lost_most_of_its_factors_keeps_a_small_index_set() -> None:
    cfg = SlamConfig(huber_k=None)
    inc = IncrementalGraph(cfg)
    poses = [pose_key(0, k) for k in range(400)]
    mark = landmark_key(0)
    point = np.array([20.0, 5.0])
    factors: list[gtsam.NonlinearFactor] = [pose_prior_factor(poses[0], Pose2D(0, 0, 0), cfg)]
    values = gtsam.Values()
    for k, key in enumerate(poses):
        values.insert(key, gtsam.Pose2(0.1 * k, 0.0, 0.0))
        if k:
            factors.append(odometry_factor(poses[k - 1], key, Odometry(0.1, 0.0, 0.0), cfg))
        factors.append(bearing_factor(key, mark, math.atan2(5.0, 20.0 - 0.1 * k), SIGMA, None))
    factors.append(landmark_prior_factor(mark, point, 10.0))
    values.insert(mark, point)
    inc.update(factors, values)
    bearings = [i for i in inc.factors_of(mark) if inc.is_bearing(i)]
    full = sys.getsizeof(inc._key_factors[mark])
    assert len(bearings) == 400 and full > 16 * 1024
    kept = bearings[::50]
    inc.update(drop=[i for i in bearings if i not in kept])
    assert [i for i in inc.factors_of(mark) if inc.is_bearing(i)] == kept
    assert sys.getsizeof(inc._key_factors[mark]) < full / 16
    assert _table_bytes_ok(inc) == []


def test_the_factor_index_of_a_lifelong_map_stays_within_16_slots_per_element() -> None:
    """Keyframes and the window come and go; a landmark's index set held the table of
    its busiest moment until it is rebuilt."""
    frames, _, _ = circle_frames(500, seed=12, n_landmarks=30, step=0.3)
    config = SlamConfig(landmark_cap=10, pose_window=60, window_observations=None, max_keyframes=30)
    slam = BearingSlam(config, rng=np.random.default_rng(5))
    largest = 0
    for f in frames:
        slam.process(f, with_covariance=False)
        assert _table_bytes_ok(slam.graph) == [], slam.frame_count
        largest = max(largest, max(len(s) for s in slam.graph._key_factors.values()))
    assert slam.removal_count > 0, "the run must remove landmarks"
    assert largest > 40, "some landmark must gather many factors"
