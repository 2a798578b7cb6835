"""The check of a converged filter against the robot's recent frames (labelled maps), and
the localiser relocalising only at a pose that check confirms."""

from __future__ import annotations

import math
import pickle
from collections.abc import Callable

import numpy as np

from graph.localiser import (
    INITIALISING,
    RELOCALISED,
    Localiser,
    LocaliserConfig,
    RobotTrack,
    StepResult,
)
from graph.particles import FilterConfig, FilterEstimate, ParticleFilter
from graph.window_check import (
    CONFIRMED,
    REFUTED,
    WAIT,
    WindowCheckConfig,
    WindowFrame,
    check_window,
)
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


def test_landmarks_with_a_sigma_widen_the_pose_and_make_the_check_wait() -> None:
    # The same frames: held landmarks confirm; landmarks that may sit 0.5 m off leave the
    # pose that much less sure, beyond what the convergence test asks, so it waits.
    frames, truth = _window(10)
    held = check_window(truth, TIGHT, frames, FilterConfig())
    loose = check_window(
        truth, TIGHT, frames, FilterConfig(), WindowCheckConfig(landmark_sigma_m=0.5)
    )
    assert held.verdict == CONFIRMED
    assert loose.verdict == WAIT
    assert (
        np.linalg.eigvalsh(loose.covariance[:2, :2])[-1]
        > 4 * np.linalg.eigvalsh(held.covariance[:2, :2])[-1]
    )
    # the landmarks give a little to the bearings' noise: the pose moves, well within sigma
    assert float(np.hypot(*(loose.pose_xytheta[:2] - held.pose_xytheta[:2]))) < 0.2


def test_the_localisers_config_carries_the_check_and_an_older_one_loads_with_the_default() -> None:
    wide = LocaliserConfig(window_check=WindowCheckConfig(landmark_sigma_m=0.3))
    assert pickle.loads(pickle.dumps(wide)).window_check.landmark_sigma_m == 0.3
    older = LocaliserConfig.__new__(LocaliserConfig)
    older.__setstate__(tuple(getattr(wide, f) for f in wide.__slots__)[:-1])
    assert older.window_check == WindowCheckConfig()


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


def _searching(
    verify_window: int, rng: np.random.Generator
) -> tuple[Localiser, RobotTrack, np.ndarray]:
    """A localiser whose robot searched over the test world's first 30 frames, its filter
    converged at the 30th true pose (returned)."""
    config = LocaliserConfig(confirm_frames=1, learn_places=False, verify_window=verify_window)
    loc = Localiser(config)
    frames, truth = _window(30)
    track = RobotTrack(
        ParticleFilter.around(truth, (0.02, 0.02, 0.005), config.filter, rng=rng), INITIALISING
    )
    track.window.extend(frames)
    loc.robots["r"] = track
    return loc, track, truth


def _converged_at_wrong_pose(verify_window: int) -> str:
    """A robot's 30 true frames, then a filter converged (by sample impoverishment) at a
    pose 1.5 m off that fits the next frame's single bearing: the status it gets."""
    rng, world = np.random.default_rng(0), np.random.default_rng(1)
    loc, track, _ = _searching(verify_window, rng)
    config = loc.config
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


def _step_at(
    loc: Localiser,
    pose: np.ndarray,
    odometry: np.ndarray | None,
    rng: np.random.Generator,
    world: np.random.Generator,
    verify: Callable[[FilterEstimate], bool] | None = None,
) -> StepResult:
    """The searching robot's next frame: every landmark the test world shows from `pose`."""
    labels, z = _frame(pose, world)
    return loc.step(
        "r",
        odometry=None if odometry is None else tuple(float(v) for v in odometry),
        dt_s=0.2,
        labels=labels,
        bearings_rad=z,
        landmarks=WORLD,
        graph_pose=None,
        rng=rng,
        sigmas_rad=[SIGMA] * len(z),
        verify=verify,
    )


def test_a_filter_converged_at_the_true_pose_is_relocalised_on_a_labelled_map() -> None:
    """The same 30 frames, the filter converged at the truth of the 30th and moved by the
    odometry to the next frame: the check confirms it."""
    rng, world = np.random.default_rng(0), np.random.default_rng(1)
    loc, _, last = _searching(LocaliserConfig().verify_window, rng)
    nxt = _circle_pose(30)
    result = _step_at(loc, nxt, _odometry(last, nxt), rng, world)
    assert result.status == RELOCALISED and result.anchor
    assert float(np.hypot(*(result.estimate.pose_xytheta[:2] - nxt[:2]))) < 0.1


def test_the_callers_check_takes_precedence_over_the_window() -> None:
    def status(verify: Callable[[FilterEstimate], bool] | None) -> str:
        rng, world = np.random.default_rng(2), np.random.default_rng(3)
        loc, _, truth = _searching(LocaliserConfig().verify_window, rng)
        return _step_at(loc, truth, None, rng, world, verify=verify).status

    assert status(None) == RELOCALISED  # the window alone confirms the pose
    assert status(lambda est: False) == INITIALISING


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


# ------------------------------------------------------------------ the old-pose test
def test_frames_from_where_the_robot_was_do_not_reject_its_pose() -> None:
    """Under the hypothesis (the anchor is the pose before the frames) the statistic is
    about chi^2 with 3 dof: below the 99.9 % quantile on frames that continue from it."""
    from graph.window_check import old_pose_rejection

    for seed in range(3):
        frames, truth = _window(21, seed)
        anchor = _circle_pose(0)
        stat = old_pose_rejection(anchor, TIGHT, frames[1:], FilterConfig(), latest_xytheta=[truth])
        assert -1e-6 <= stat < 16.27


def test_frames_from_elsewhere_reject_the_old_pose_even_before_the_filter_finds_the_new() -> None:
    """The robot carried 1.5 m away between the anchor and the frames: the frames reject
    the anchor whether H1 starts at the new pose (the filter found it) or only from the
    old one (the optimiser moves a pose without a prior to where the bearings fit)."""
    from graph.window_check import old_pose_rejection

    frames, truth = _window(11)
    moved = _circle_pose(0) + np.array([1.5, 0.0, 0.0])
    found = old_pose_rejection(moved, TIGHT, frames[1:], FilterConfig(), latest_xytheta=[truth])
    alone = old_pose_rejection(moved, TIGHT, frames[1:], FilterConfig())
    assert found > 100.0
    assert alone > 100.0


def test_a_wider_old_pose_is_rejected_later() -> None:
    """What the test can tell shrinks with the old pose's covariance: a 1 m offset that a
    tight anchor's first three frames reject stays unrejected under a metre-wide one."""
    from graph.window_check import old_pose_rejection

    frames, truth = _window(11)
    moved = _circle_pose(0) + np.array([1.0, 0.0, 0.0])
    tight = old_pose_rejection(moved, TIGHT, frames[1:4], FilterConfig(), latest_xytheta=[truth])
    wide = np.diag([1.0, 1.0, 0.1])
    loose = old_pose_rejection(moved, wide, frames[1:4], FilterConfig(), latest_xytheta=[truth])
    assert tight > 16.27 > loose


def test_a_wrong_bearing_does_not_reject_the_old_pose() -> None:
    """One bearing 30 deg off in each of two frames (MRCLAM has such outliers): H1 can
    fit them and H0 cannot, but the Cauchy loss keeps what they cost to a few sigmas'
    worth, below the 99.9 % quantile that a kidnap's frames soon exceed."""
    from graph.window_check import WindowFrame, old_pose_rejection

    frames, truth = _window(11)
    spoilt = list(frames[1:])
    for k in (2, 6):
        f = spoilt[k]
        z = f.bearings_rad.copy()
        z[0] += math.radians(30.0)
        spoilt[k] = WindowFrame(f.odometry, f.dt_s, f.landmarks_xy, z, f.sigmas_rad)
    stat = old_pose_rejection(
        _circle_pose(0), TIGHT, spoilt, FilterConfig(), latest_xytheta=[truth]
    )
    assert stat < 16.27


def test_one_landmark_misread_for_several_frames_does_not_reject_the_old_pose() -> None:
    """A landmark's code misread seven frames running in frames that saw nothing else
    (its bearings put on another landmark; the test's window starts at the first frame
    the graph's pose does not explain): the free solution explains them and the old pose
    cannot, beyond the gate, but left out, no bearing remains: no rejection. A kidnap's
    frames reject without any one landmark as well."""
    from graph.window_check import WindowFrame, old_pose_rejection, rejects_old_pose

    frames, truth = _window(8)
    wrong = frames[1].landmarks_xy[:1] + np.array([1.5, -1.0])  # the code misread names it
    misread = [
        WindowFrame(f.odometry, f.dt_s, wrong, f.bearings_rad[:1], f.sigmas_rad[:1])
        for f in frames[1:]
    ]
    anchor, cfg = _circle_pose(0), FilterConfig()
    assert old_pose_rejection(anchor, TIGHT, misread, cfg, latest_xytheta=[truth]) > 20.0
    assert not rejects_old_pose(anchor, TIGHT, misread, cfg, 20.0, latest_xytheta=[truth])[0]
    frames, truth = _window(11)
    moved = anchor + np.array([1.5, 0.0, 0.0])
    assert rejects_old_pose(moved, TIGHT, frames[1:], cfg, 20.0, latest_xytheta=[truth])[0]
