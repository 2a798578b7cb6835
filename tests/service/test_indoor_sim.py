"""The simulated indoor world: determinism, conventions, visibility, motion."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest

from graph.angles import wrap_angles
from service.offline.datasets.indoor_sim import (
    IndoorWorld,
    SimRun,
    bearings_from_pose,
    make_world,
    simulate,
    write_run,
)
from service.offline.evaluation import dead_reckoning, read_tum
from service.offline.frame_files import read_frames


@pytest.fixture(scope="module")
def world() -> IndoorWorld:
    return make_world(rng=np.random.default_rng(7))


@pytest.fixture(scope="module")
def run(world: IndoorWorld) -> SimRun:
    return simulate(world, frames=5000, rng=np.random.default_rng(8))


def test_world_layout(world: IndoorWorld) -> None:
    assert world.n_rooms == 9
    assert world.landmarks.shape == (225, 2)
    assert len(np.unique(world.landmark_ids)) == 225
    assert np.bincount(world.landmark_rooms).tolist() == [25] * 9
    np.testing.assert_array_equal(world.room_of(world.landmarks), world.landmark_rooms)
    assert len(world.doors) == 12  # 3 x 3 grid: 6 + 6 shared walls
    assert sorted(r for _, r in world.neighbours(4)) == [1, 3, 5, 7]
    for d, (a, b) in enumerate(world.door_rooms):
        # a door centre lies on the wall the two rooms share
        assert np.linalg.norm(world.room_centre(a) - world.room_centre(b)) == world.room_size_m
        mid = 0.5 * (world.room_centre(a) + world.room_centre(b))
        np.testing.assert_allclose(world.doors[d], mid)


def test_landmarks_near_walls_and_clear_of_the_path(world: IndoorWorld, run: SimRun) -> None:
    local = world.landmarks - np.array([world.room_origin(r) for r in world.landmark_rooms])
    to_wall = np.minimum(local, world.room_size_m - local).min(axis=1)
    assert np.all(to_wall >= 0.05) and np.all(to_wall <= 0.5)
    path = run.ground_truth.xy
    nearest = np.min(np.linalg.norm(path[:, None, :] - world.landmarks[None], axis=2))
    assert nearest >= 0.5


def test_same_seed_same_frames() -> None:
    runs = [
        simulate(make_world(rng=np.random.default_rng(3)), frames=300, rng=np.random.default_rng(4))
        for _ in range(2)
    ]
    assert runs[0].frames == runs[1].frames
    np.testing.assert_array_equal(runs[0].ground_truth.xy, runs[1].ground_truth.xy)
    world = make_world(rng=np.random.default_rng(3))
    other = simulate(world, frames=300, rng=np.random.default_rng(5))
    assert other.frames != runs[0].frames


def test_convention_bearings_ccw_from_forward() -> None:
    pose = np.array([1.0, 2.0, math.pi / 2])  # facing +y
    points = np.array([[1.0, 5.0], [-2.0, 2.0], [4.0, 2.0], [1.0, -1.0]])
    expected = [0.0, math.pi / 2, -math.pi / 2, math.pi]  # ahead, left, right, behind
    np.testing.assert_allclose(bearings_from_pose(pose, points), expected, atol=1e-12)


def test_convention_noise_free_bearing_rays_hit_their_landmarks(world: IndoorWorld) -> None:
    run = simulate(world, frames=400, rng=np.random.default_rng(9), bearing_sigma_rad=0.0)
    where = dict(zip(world.landmark_ids.tolist(), world.landmarks, strict=True))
    count = 0
    for frame, pose in zip(run.frames, run.ground_truth.poses(), strict=True):
        for ob in frame.observations:
            assert ob.sigma_rad is None
            ray = np.array([math.cos(pose[2] + ob.bearing_rad), math.sin(pose[2] + ob.bearing_rad)])
            rel = where[int(ob.label)] - pose[:2]
            assert abs(ray[0] * rel[1] - ray[1] * rel[0]) < 1e-9  # on the line
            assert ray @ rel > 0  # and in front along it
            count += 1
    assert count > 1000


def test_observations_stay_in_the_robots_room(world: IndoorWorld, run: SimRun) -> None:
    rooms = world.room_of(run.ground_truth.xy)
    ids, id_rooms = world.landmark_ids.tolist(), world.landmark_rooms.tolist()
    landmark_room = dict(zip(ids, id_rooms, strict=True))
    for frame, room, pose in zip(run.frames, rooms, run.ground_truth.poses(), strict=True):
        assert len(frame.observations) <= 10
        for ob in frame.observations:
            assert landmark_room[int(ob.label)] == room
        if frame.observations:
            labels = [int(ob.label) for ob in frame.observations]
            dist = np.linalg.norm(world.landmarks[labels] - pose[:2], axis=1)
            assert np.all(dist <= 5.0)
            assert np.all(np.diff(dist) >= 0)  # nearest first
    assert sum(len(f.observations) for f in run.frames) > 5 * len(run.frames)


def test_every_room_visited_many_times(world: IndoorWorld, run: SimRun) -> None:
    rooms = world.room_of(run.ground_truth.xy)
    assert set(rooms.tolist()) == set(range(world.n_rooms))
    entries = np.bincount(rooms[1:][np.diff(rooms) != 0], minlength=world.n_rooms)
    assert entries.sum() >= 20  # room changes: revisits, hence loop closures
    assert run.frames[0].initial_pose is not None and rooms[0] == 0


def test_bearings_wrapped(run: SimRun) -> None:
    bearings = np.array([ob.bearing_rad for f in run.frames for ob in f.observations])
    assert np.all(bearings > -math.pi) and np.all(bearings <= math.pi)
    assert bearings.min() < -3.0 and bearings.max() > 3.0  # all around the robot


def test_noise_free_odometry_composes_to_the_truth(world: IndoorWorld) -> None:
    run = simulate(world, frames=2000, rng=np.random.default_rng(10), odometry_noise=(0, 0, 0))
    dr = dead_reckoning(run.frames)
    np.testing.assert_allclose(dr.xy, run.ground_truth.xy, atol=1e-9)
    np.testing.assert_allclose(wrap_angles(dr.theta - run.ground_truth.theta), 0.0, atol=1e-9)
    pose0 = run.frames[0].initial_pose
    assert pose0 is not None
    assert [pose0.x, pose0.y, pose0.theta] == pytest.approx(run.ground_truth.poses()[0])


def test_noisy_odometry_drifts(run: SimRun) -> None:
    dr = dead_reckoning(run.frames)
    error = np.linalg.norm(dr.xy - run.ground_truth.xy, axis=1)
    assert error[-1] > 0.05 and error[10] < 0.1


def test_twenty_thousand_frames_are_fast(world: IndoorWorld) -> None:
    start = time.perf_counter()
    run = simulate(world, frames=20_000, rng=np.random.default_rng(11))
    assert len(run.frames) == 20_000
    assert time.perf_counter() - start < 10.0


def test_write_run(tmp_path: Path, world: IndoorWorld) -> None:
    run = simulate(world, frames=50, rng=np.random.default_rng(12))
    write_run(run, tmp_path / "frames.jsonl", tmp_path / "gt.tum")
    assert list(read_frames(tmp_path / "frames.jsonl")) == run.frames
    gt = read_tum(tmp_path / "gt.tum")
    np.testing.assert_allclose(gt.xy, run.ground_truth.xy, atol=1e-6)
