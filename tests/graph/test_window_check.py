"""The check of a converged filter against the robot's recent frames (labelled maps), and
the localiser relocalising only at a pose that check confirms."""

from __future__ import annotations

import math
import pickle

import numpy as np

from graph.localiser import INITIALISING, RELOCALISED, Localiser, LocaliserConfig, RobotTrack
from graph.particles import FilterConfig, ParticleFilter
from graph.window_check import CONFIRMED, REFUTED, WAIT, WindowFrame, check_window
from tests.graph.test_localiser import WORLD, _frame
from tests.graph.test_particles import _circle_pose, _observe, _odometry

SIGMA = math.radians(1.0)
TIGHT = np.diag([0.01, 0.01, 1e-4])


def _window(frames: int, seed: int = 0) -> tuple[list[WindowFrame], np.ndarray]:
    """A robot's frames along the test world's circle and its last true pose."""
    rng = np.random.default_rng(seed)
    out, previous, truth = [], None, _circle_pose(0)
    for k in range(frames):
        truth = _circle_pose(k)
        lm, z = _observe(truth, rng)
        odo = None if previous is None else _odometry(previous, truth)
        out.append(WindowFrame(odo, 0.2, lm, z, np.full(len(z), SIGMA)))
        previous = truth
    return out, truth


def test_the_true_pose_is_confirmed_by_a_window_that_determines_it() -> None:
    frames, truth = _window(30)
    got = check_window(truth, TIGHT, frames, FilterConfig())
    assert got.verdict == CONFIRMED
    assert float(np.hypot(*(got.pose_xytheta[:2] - truth[:2]))) < 0.1
    assert got.misfit_share <= 0.05
    assert got.bearings == sum(len(f.bearings_rad) for f in frames)


def test_a_pose_the_window_does_not_fit_is_refuted() -> None:
    frames, truth = _window(30)
    wrong = truth + np.array([1.5, -1.0, math.radians(25.0)])
    assert check_window(wrong, TIGHT, frames, FilterConfig()).verdict == REFUTED


def test_one_bearing_is_not_enough_to_be_sure() -> None:
    frames, truth = _window(1)
    one = frames[0]
    frames = [
        WindowFrame(None, 0.0, one.landmarks_xy[:1], one.bearings_rad[:1], one.sigmas_rad[:1])
    ]
    assert check_window(truth, TIGHT, frames, FilterConfig()).verdict == WAIT


def _on_the_ray(truth: np.ndarray, landmark: np.ndarray, metres: float) -> np.ndarray:
    """A pose `metres` further from `landmark` along the ray to it: same heading, so the
    same bearing to that landmark."""
    d = truth[:2] - landmark
    return np.array([*(truth[:2] + metres * d / np.linalg.norm(d)), truth[2]])


def _converged_at_wrong_pose(verify_window: int) -> str:
    """A robot's 30 true frames, then a filter converged (by sample impoverishment) at a
    pose 1.5 m off that fits the next frame's single bearing: the status it gets."""
    config = LocaliserConfig(confirm_frames=1, learn_places=False, verify_window=verify_window)
    loc = Localiser(config)
    rng, world = np.random.default_rng(0), np.random.default_rng(1)
    frames, truth = _window(30)
    track = RobotTrack(
        ParticleFilter.around(truth, (0.02, 0.02, 0.005), config.filter, rng=rng), INITIALISING
    )
    track.window.extend(frames)
    loc.robots["r"] = track
    nxt = _circle_pose(30)
    labels, z = _frame(nxt, world)
    label = labels[0]
    wrong = _on_the_ray(nxt, WORLD[label], 1.5)
    track.pf = ParticleFilter.around(wrong, (0.02, 0.02, 0.005), config.filter, rng=rng)
    result = loc.step(
        "r",
        odometry=None,  # the filter's cloud is placed for this frame already
        dt_s=0.2,
        labels=[label],
        bearings_rad=[z[0]],
        landmarks=WORLD,
        graph_pose=None,
        rng=rng,
        sigmas_rad=[SIGMA],
    )
    assert result.estimate.converged or result.status != RELOCALISED
    return result.status


def test_a_filter_converged_at_a_wrong_pose_is_not_relocalised_on_a_labelled_map() -> None:
    assert _converged_at_wrong_pose(verify_window=150) == INITIALISING
    # Without the check, the same filter reports the wrong pose relocalised.
    assert _converged_at_wrong_pose(verify_window=0) == RELOCALISED


def test_the_callers_check_takes_precedence_over_the_window() -> None:
    frames, truth = _window(30)
    config = LocaliserConfig(confirm_frames=1, learn_places=False)
    loc = Localiser(config)
    rng, world = np.random.default_rng(2), np.random.default_rng(3)
    track = RobotTrack(
        ParticleFilter.around(truth, (0.02, 0.02, 0.005), config.filter, rng=rng), INITIALISING
    )
    track.window.extend(frames)  # the window alone would confirm the pose
    loc.robots["r"] = track
    labels, z = _frame(truth, world)
    result = loc.step(
        "r",
        odometry=None,
        dt_s=0.2,
        labels=labels,
        bearings_rad=z,
        landmarks=WORLD,
        graph_pose=None,
        rng=rng,
        verify=lambda est: False,
    )
    assert result.status == INITIALISING


def test_a_track_pickled_before_the_window_existed_loads_with_an_empty_one() -> None:
    rng = np.random.default_rng(0)
    track = RobotTrack(
        ParticleFilter.around(_circle_pose(0), (0.1, 0.1, 0.1), FilterConfig(), rng=rng),
        INITIALISING,
    )
    state = dict(track.__dict__)
    del state["window"]
    old = RobotTrack.__new__(RobotTrack)
    old.__setstate__(state)
    again = pickle.loads(pickle.dumps(old))
    assert list(again.window) == [] and again.status == INITIALISING
