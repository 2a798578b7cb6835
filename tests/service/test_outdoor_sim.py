"""The simulated outdoor world: road geometry, tree clearances, odometry, bearings."""

from __future__ import annotations

import math

import numpy as np
import pytest

from graph.angles import wrap_angles
from service.offline.datasets.indoor_sim import bearings_from_pose
from service.offline.datasets.outdoor_sim import OutdoorWorld, make_outdoor_world, simulate_outdoor
from service.offline.evaluation import ate_rmse, dead_reckoning


@pytest.fixture(scope="module")
def world() -> OutdoorWorld:
    return make_outdoor_world(rng=np.random.default_rng(0))


def test_convention_the_road_starts_heading_plus_x_and_turns_left(world: OutdoorWorld) -> None:
    r = world.corner_radius_m
    np.testing.assert_allclose(world.road[0], [r, 0.0, 0.0], atol=1e-12)
    # A quarter lap of bends and straights later: the right-hand side, heading +y.
    s = world.length_m - 2 * r + 0.5 * math.pi * r + 1.0
    np.testing.assert_allclose(
        world.road_pose(np.array([s]))[0], [world.length_m, r + 1.0, math.pi / 2], atol=1e-9
    )
    # The heading is the direction of travel, everywhere (to a 0.25 m chord straddling
    # a straight and a bend: 0.25 / (2 r) of the bend's turn at most).
    step = np.diff(world.road[:, :2], axis=0)
    along = np.arctan2(step[:, 1], step[:, 0])
    mid = world.road[:-1, 2] + 0.5 * np.diff(np.unwrap(world.road[:, 2]))
    assert np.max(np.abs(wrap_angles(along - mid))) < 0.25 / (2 * r)


def test_the_road_is_a_closed_loop_of_its_length(world: OutdoorWorld) -> None:
    r = world.corner_radius_m
    expected = 2 * (world.length_m + world.width_m) - (8 - 2 * math.pi) * r
    assert world.loop_m == pytest.approx(expected)
    closed = np.vstack([world.road[:, :2], world.road[:1, :2]])
    gaps = np.hypot(*np.diff(closed, axis=0).T)
    assert np.all(gaps <= 0.25 + 1e-9) and gaps.sum() == pytest.approx(world.loop_m, rel=1e-3)


def test_trees_stand_5_to_80_m_from_the_road(world: OutdoorWorld) -> None:
    assert world.landmarks.shape == (150, 2) and len(set(world.landmark_ids.tolist())) == 150
    assert np.all(world.clearance_m >= 5.0 - 0.13) and np.all(world.clearance_m <= 80.0)
    assert np.mean(world.clearance_m > 15.0) > 0.5  # most beyond an indoor map's depth range
    again = make_outdoor_world(rng=np.random.default_rng(0))
    np.testing.assert_array_equal(again.landmarks, world.landmarks)


def test_noise_free_odometry_composes_to_the_truth_and_bearings_hit_the_trees(
    world: OutdoorWorld,
) -> None:
    run = simulate_outdoor(
        world,
        laps=0.5,
        rng=np.random.default_rng(1),
        odometry_noise=(0.0, 0.0, 0.0),
        odometry_scale=1.0,
        bearing_sigma_rad=0.0,
    )
    assert ate_rmse(dead_reckoning(run.frames), run.ground_truth) < 1e-9
    where = dict(zip(map(str, world.landmark_ids.tolist()), world.landmarks, strict=True))
    for frame, pose in zip(run.frames[::25], run.ground_truth.poses()[::25], strict=True):
        assert 0 < len(frame.observations) <= 12
        trees = np.array([where[o.label] for o in frame.observations])
        assert np.all(np.hypot(*(trees - pose[:2]).T) <= 100.0)
        got = np.array([o.bearing_rad for o in frame.observations])
        np.testing.assert_allclose(got, bearings_from_pose(pose, trees), atol=1e-12)


def test_odometry_drifts_with_its_scale_error_and_noise(world: OutdoorWorld) -> None:
    run = simulate_outdoor(world, rng=np.random.default_rng(2))
    assert len(run.frames) == round(1.5 * world.loop_m / 0.75) + 1
    travelled = sum(f.odometry.dx for f in run.frames[1:] if f.odometry is not None)
    assert travelled == pytest.approx(1.01 * 1.5 * world.loop_m, rel=0.01)
    dead = dead_reckoning(run.frames)
    assert 1.0 < ate_rmse(dead, run.ground_truth) < 50.0
    sigmas = {o.sigma_rad for f in run.frames for o in f.observations}
    assert sigmas == {math.radians(1.0)}
