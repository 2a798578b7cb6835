"""Places: landmark selection, yaw-invariant recognition, decay, transitions, query time."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from graph.angles import wrap_angle, wrap_angles
from graph.places import LandmarkCandidate, PlaceConfig, PlaceMap, select_landmarks
from graph.types import Pose2D


def _world(rng: np.random.Generator, n: int = 40, size: float = 20.0) -> dict[str, np.ndarray]:
    return {str(i): rng.uniform(0.0, size, 2) for i in range(n)}


def _candidates(world: dict[str, np.ndarray]) -> list[LandmarkCandidate]:
    return [
        LandmarkCandidate(label, int(label), (float(xy[0]), float(xy[1])), np.eye(2) * 0.01, 1.0)
        for label, xy in world.items()
    ]


def _observe(world: dict[str, np.ndarray], pose: np.ndarray, max_depth: float = 8.0):
    labels, bearings = [], []
    for label, xy in world.items():
        d = xy - pose[:2]
        if np.hypot(*d) <= max_depth:
            labels.append(label)
            bearings.append(wrap_angle(math.atan2(d[1], d[0]) - pose[2]))
    return labels, bearings


def test_selection_spreads_over_directions() -> None:
    cands = [
        LandmarkCandidate(f"e{i}", i, (3.0, 0.1 * i), np.eye(2) * 0.01, 1.0) for i in range(10)
    ]  # ten landmarks bunched ahead
    cands += [
        LandmarkCandidate("w", 20, (-3.0, 0.0), np.eye(2) * 0.01, 0.5),
        LandmarkCandidate("n", 21, (0.0, 3.0), np.eye(2) * 0.01, 0.5),
    ]
    chosen = select_landmarks(Pose2D(0.0, 0.0, 0.0), cands, PlaceConfig(max_landmarks=4))
    labels = [lm.label for lm in chosen]
    assert len(labels) == 4
    assert "w" in labels and "n" in labels  # less reliable, but the only ones behind / left
    assert all(lm.depth_m == pytest.approx(math.hypot(3.0, 0.0), abs=1.0) for lm in chosen)


def test_convention_place_bearings_and_depth_variance() -> None:
    cov = np.diag([0.04, 0.01])  # 0.2 m along x, 0.1 m along y
    cands = [
        LandmarkCandidate("a", 0, (1.0, 3.0), cov, 1.0),
        LandmarkCandidate("b", 1, (4.0, 2.0), cov, 1.0),
    ]
    chosen = {
        lm.label: lm for lm in select_landmarks(Pose2D(1.0, 2.0, math.pi / 2), cands, PlaceConfig())
    }
    # facing +y: 'a' straight ahead, 'b' to the right
    assert chosen["a"].bearing_rad == pytest.approx(0.0, abs=1e-12)
    assert chosen["b"].bearing_rad == pytest.approx(-math.pi / 2, abs=1e-12)
    assert chosen["a"].depth_var_m2 == pytest.approx(0.01)
    assert chosen["b"].depth_var_m2 == pytest.approx(0.04)


@pytest.mark.parametrize("yaw_deg", [0, 45, 90, 135, 180, 225, 270, 315, 359])
def test_recognition_is_yaw_invariant(yaw_deg: int) -> None:
    rng = np.random.default_rng(1)
    world = _world(rng)
    places = PlaceMap(PlaceConfig())
    refs = [
        np.array([x, y, rng.uniform(-math.pi, math.pi)]) for x in (3, 10, 17) for y in (3, 10, 17)
    ]
    for ref in refs:
        assert places.learn(Pose2D(*ref), _candidates(world), robot="r", frame=0, stamp=0.0)
    hits = 0
    for i, ref in enumerate(refs):
        pose = ref + np.array([0.3, -0.2, math.radians(yaw_deg)])
        labels, bearings = _observe(world, pose)
        bearings = wrap_angles(np.asarray(bearings) + rng.normal(0, math.radians(1), len(bearings)))
        rec = places.recognise(labels, bearings.tolist())
        hits += rec.best == i
        heading = wrap_angle(ref[2] - rec.yaw_offsets_rad[0])
        assert abs(wrap_angle(heading - pose[2])) < math.radians(10)
    assert hits == len(refs)


def test_decay_prefers_places_near_the_current_one() -> None:
    # Two identical-looking places (same relative bearings): the decay decides.
    world = {
        "a": np.array([1.0, 0.0]),
        "b": np.array([0.0, 1.0]),
        "c": np.array([11.0, 0.0]),
        "d": np.array([10.0, 1.0]),
    }
    places = PlaceMap(PlaceConfig(max_depth_m=2.0))
    cands = [
        LandmarkCandidate(k, i, (float(v[0]), float(v[1])), np.eye(2) * 0.01, 1.0)
        for i, (k, v) in enumerate(world.items())
    ]
    places.learn(Pose2D(0.0, 0.0, 0.0), cands, robot="r", frame=0, stamp=0.0)
    places.learn(Pose2D(10.0, 0.0, 0.0), cands, robot="r", frame=1, stamp=1.0)
    labels = ["a", "b", "c", "d"]
    bearings = [0.0, math.pi / 2, 0.0, math.pi / 2]
    assert places.recognise(labels, bearings, current=1).best == 1
    assert places.recognise(labels, bearings, current=0).best == 0
    undecayed = places.recognise(labels, bearings)
    assert undecayed.scores[0] == pytest.approx(undecayed.scores[1])


def test_learning_rule_and_transitions() -> None:
    rng = np.random.default_rng(2)
    world = _world(rng)
    places = PlaceMap(PlaceConfig(learn_distance_m=1.5))
    assert places.should_learn((5.0, 5.0), 1.0)  # no place yet
    places.learn(Pose2D(5.0, 5.0, 0.0), _candidates(world), robot="r", frame=0, stamp=0.0)
    assert places.visit("r", 0) is None
    assert not places.should_learn((5.5, 5.0), 0.9)
    assert not places.should_learn((5.5, 5.0), 0.1)  # weak, but close to the place
    assert places.should_learn((6.0, 5.0), 0.1)  # weak and half-way out
    assert places.should_learn((7.0, 5.0), 0.9)  # far
    places.learn(Pose2D(5.0, 8.0, 0.0), _candidates(world), robot="r", frame=5, stamp=5.0)
    t = places.visit("r", 1)
    assert t is not None and (t.source, t.target) == (0, 1)
    assert t.heading_rad == pytest.approx(math.pi / 2) and t.distance_m == pytest.approx(3.0)
    places.visit("r", 0)
    places.visit("r", 1)
    assert places.transitions[(0, 1)].count == 2 and places.transitions[(1, 0)].count == 1


def test_query_time_for_100_places() -> None:
    rng = np.random.default_rng(3)
    world = _world(rng, n=200, size=60.0)
    places = PlaceMap(PlaceConfig())
    for _ in range(100):
        x, y = rng.uniform(5, 55, 2)
        places.learn(Pose2D(x, y, 0.0), _candidates(world), robot="r", frame=0, stamp=0.0)
    assert len(places) == 100
    labels, bearings = _observe(world, np.array([30.0, 30.0, 1.0]))
    times = []
    for _ in range(50):
        t0 = time.perf_counter()
        places.recognise(labels, bearings, current=3)
        times.append(time.perf_counter() - t0)
    assert float(np.median(times)) < 0.010
