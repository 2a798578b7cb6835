"""The localiser's status machine on a small synthetic world (forward-looking sensor)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from graph.angles import wrap_angle
from graph.localiser import (
    INITIALISING,
    LOST,
    RELOCALISED,
    TRACKING,
    Localiser,
    LocaliserConfig,
    RobotTrack,
    StepResult,
    _held,
)
from graph.window_check import CONFIRMED, WAIT, WindowCheckConfig, WindowFrame
from tests.graph.test_particles import LANDMARKS, _circle_pose, _observe, _odometry

WORLD = {str(i): xy for i, xy in enumerate(LANDMARKS)}
LABEL_OF = {tuple(xy): str(i) for i, xy in enumerate(LANDMARKS)}


def _frame(pose: np.ndarray, rng: np.random.Generator) -> tuple[list[str], list[float]]:
    lm, z = _observe(pose, rng)
    return [LABEL_OF[tuple(xy)] for xy in lm], z.tolist()


def test_initialising_relocalised_tracking_lost_and_back() -> None:
    loc = Localiser()
    kidnap = 60
    statuses, errors = _kidnap_run(loc, kidnap, graph_from_start=False, frames=140)
    assert statuses[0] == INITIALISING
    first = statuses.index(RELOCALISED)
    assert first <= 20
    assert statuses[first + 1] == TRACKING
    assert statuses[kidnap - 1] == TRACKING
    lost = statuses.index(LOST, kidnap)
    assert lost - kidnap <= 15
    again = statuses.index(RELOCALISED, lost)
    assert statuses[-1] == TRACKING
    assert len(errors) == 2 and errors[1][0] == again
    for _, dist, yaw in errors:
        assert dist < 0.3 and yaw < math.radians(8)
    assert len(loc.places) >= 1  # learnt automatically while tracking


def test_proposal_favours_places_only_as_far_as_recognition_tells_them_apart() -> None:
    """Places whose scores tie (one landmark seen, which all of them hold) get no more
    proposals than anywhere else; a place that stands out gets most of them."""
    from graph.places import Recognition

    loc = Localiser()
    track_pose = np.array([1.0, 1.0, 0.0])
    for k, xy in enumerate([(1.0, 1.0), (5.0, 5.0), (1.0, 5.0), (5.0, 1.0)]):
        loc.learn("r", np.array([*xy, 0.0]), WORLD, frame=k, stamp=float(k))
    assert len(loc.places) == 4
    ids = np.arange(4)
    bounds = (-1.0, -1.0, 7.0, 7.0)
    rng = np.random.default_rng(0)
    near = []
    for scores in ([0.5, 0.5, 0.5, 0.5], [1.0, 0.1, 0.1, 0.1]):
        rec = Recognition(ids, np.array(scores), np.zeros(4))
        draw = loc.proposal(rec, np.zeros((0, 2)), np.zeros(0), bounds)(4000, rng)
        near.append(float(np.mean(np.hypot(*(draw[:, :2] - track_pose[:2]).T) < 1.0)))
    uniform = math.pi / 64.0  # a 1 m disc's share of the 8 m x 8 m extent
    assert near[0] == pytest.approx(uniform, abs=0.02)
    assert near[1] > 0.3  # 0.63 of the draws around place 0 (sigma 0.75 m): ~0.39


def _tracked(rng: np.random.Generator) -> tuple[Localiser, np.ndarray, list[str], list[float]]:
    """A localiser tracking robot "r" at the graph's pose (first frame of the circle)."""
    loc = Localiser()
    truth = _circle_pose(0)
    labels, z = _frame(truth, np.random.default_rng(7))
    assert _statuses(loc, truth, 1, rng, labels, z) == [TRACKING]
    return loc, truth, labels, z


def _statuses(
    loc: Localiser,
    graph: np.ndarray,
    frames: int,
    rng: np.random.Generator,
    labels: list[str] | None = None,
    z: list[float] | None = None,
) -> list[str]:
    out = []
    for _ in range(frames):
        result = loc.step(
            "r",
            odometry=None,
            dt_s=0.2,
            labels=labels or [],
            bearings_rad=z or [],
            landmarks=WORLD,
            graph_pose=(graph, np.diag([0.01, 0.01, 0.001])),
            rng=rng,
        )
        out.append(result.status)
    return out


def _cloud(rng: np.random.Generator, *parts: tuple[np.ndarray, int]) -> np.ndarray:
    return np.vstack([pose + rng.normal(0.0, (0.02, 0.02, 0.01), (n, 3)) for pose, n in parts])


def test_a_filter_split_between_hypotheses_does_not_make_a_tracked_robot_lost() -> None:
    """Graph and filter disagree only when the filter has converged elsewhere: a belief
    whose weight is split (injected hypotheses that one bearing cannot tell apart; its
    main mode may flip from frame to frame) has no pose to disagree with. The same
    far-away mode holding all the weight does make the robot lost."""
    from graph.particles import ParticleFilter

    rng = np.random.default_rng(0)
    far = _circle_pose(0) + np.array([3.0, 0.0, 0.5])
    loc, graph, _, _ = _tracked(rng)
    cfg = loc.config.filter
    loc.robots["r"].pf = ParticleFilter.from_poses(_cloud(rng, (far, 600), (graph, 400)), cfg)
    assert not loc.robots["r"].pf.estimate().converged
    assert np.hypot(*(loc.robots["r"].pf.estimate().pose_xytheta[:2] - far[:2])) < 0.1
    assert set(_statuses(loc, graph, 8, rng)) == {TRACKING}

    loc, graph, _, _ = _tracked(rng)
    loc.robots["r"].pf = ParticleFilter.from_poses(_cloud(rng, (far, 1000)), cfg)
    assert loc.robots["r"].pf.estimate().converged
    statuses = _statuses(loc, graph, 8, rng)
    assert statuses.index(LOST) == loc.config.lost_frames - 1


def test_a_weak_filter_is_started_again_where_the_graph_explains_the_observations() -> None:
    """A tracked robot whose filter no longer explains what it sees (its fast likelihood
    average below lost_likelihood_ratio of the slow one) counts a weak frame, towards
    `lost`, only if the graph's pose does not explain the observations either. If it
    does, the filter, not the robot, has lost track (MRCLAM-6 robots turning on the spot
    with one bearing a frame went `lost` this way while their graph was right): the
    filter starts again around the graph's pose."""
    from graph.particles import ParticleFilter, uniform_injector
    from tests.graph.test_particles import BOUNDS

    rng = np.random.default_rng(1)
    for graph_offset, weak in ((np.zeros(3), False), (np.array([1.5, -1.0, 0.8]), True)):
        loc, truth, labels, z = _tracked(rng)
        track = loc.robots["r"]
        spread = ParticleFilter.from_poses(uniform_injector(BOUNDS)(3000, rng), loc.config.filter)
        spread.w_slow, spread.w_fast = track.pf.w_slow, 0.0  # it has been failing
        track.pf = spread
        graph = truth + graph_offset
        assert _statuses(loc, graph, 1, rng, labels[:1], z[:1]) == [TRACKING]
        track = loc.robots["r"]
        assert track.weak_frames == int(weak)
        est = track.pf.estimate().pose_xytheta
        near = np.hypot(*(est[:2] - graph[:2])) < 0.2 and abs(wrap_angle(est[2] - graph[2])) < 0.1
        assert near == (not weak)


def _dead_reckon(graph: np.ndarray, odo: np.ndarray) -> np.ndarray:
    """The graph's pose moved by one odometry increment (in its own frame)."""
    c, s = math.cos(graph[2]), math.sin(graph[2])
    return graph + np.array([c * odo[0] - s * odo[1], s * odo[0] + c * odo[1], odo[2]])


def _step(
    loc: Localiser,
    k: int,
    odo: np.ndarray | None,
    labels: list[str],
    z: list[float],
    graph: np.ndarray | None,
    rng: np.random.Generator,
) -> StepResult:
    """Robot "r1"'s frame `k` (0.2 s apart) with the graph's pose `graph` (None: none)."""
    return loc.step(
        "r1",
        odometry=odo,
        dt_s=0.2,
        labels=labels,
        bearings_rad=z,
        landmarks=WORLD,
        graph_pose=None if graph is None else (graph, np.diag([0.01, 0.01, 0.001])),
        rng=rng,
        frame=k,
        stamp=0.2 * k,
    )


def _kidnap_run(
    loc: Localiser,
    kidnap: int | None,
    *,
    graph_from_start: bool,
    seed: int = 0,
    frames: int = 120,
) -> tuple[list[str], list[tuple[int, float, float]]]:
    """A robot along the circle, carried to another circle at frame `kidnap` (no
    odometry for the jump) unless None. The graph's pose dead reckons from the last
    relocalisation, or from the true first pose if `graph_from_start` (it never sees a
    kidnap). The statuses, and (frame, m, rad) errors of each relocalisation."""
    rng, world = np.random.default_rng(seed), np.random.default_rng(seed + 1)
    statuses: list[str] = []
    errors = []
    previous = graph = None
    for k in range(frames):
        moved = kidnap is not None and k >= kidnap
        truth = _circle_pose(k, centre=(4.2, 4.6)) if moved else _circle_pose(k)
        odo = None
        if previous is None and graph_from_start:
            graph = truth.copy()
        if previous is not None:
            nominal = _circle_pose(k) if k == kidnap else truth  # no odometry for the jump
            odo = _odometry(previous, nominal)
            if graph is not None:
                graph = _dead_reckon(graph, odo)
        labels, z = _frame(truth, world)
        result = _step(loc, k, odo, labels, z, graph, rng)
        statuses.append(result.status)
        if result.anchor:
            graph = result.estimate.pose_xytheta.copy()
            est = result.estimate.pose_xytheta
            errors.append(
                (k, float(np.hypot(*(est[:2] - truth[:2]))), abs(wrap_angle(est[2] - truth[2])))
            )
        if result.status == LOST:
            graph = None
        previous = truth
    return statuses, errors


def test_the_observations_reject_the_tracked_pose_after_a_kidnap() -> None:
    """With the other `lost` rules out of reach (lost_frames beyond the run), the
    old-pose test alone finds a kidnapped robot lost within a few frames of the jump, and
    a robot that was not moved is never lost."""
    config = LocaliserConfig(lost_frames=10_000)
    assert math.isfinite(config.kidnap_gate)
    for seed in range(2):
        calm, _ = _kidnap_run(Localiser(config), None, graph_from_start=True, seed=seed)
        assert LOST not in calm
        statuses, _ = _kidnap_run(Localiser(config), 60, graph_from_start=True, seed=seed)
        assert LOST not in statuses[:60]
        assert statuses.index(LOST, 60) - 60 <= 5
    off = LocaliserConfig(lost_frames=10_000, kidnap_window=0)
    assert LOST not in _kidnap_run(Localiser(off), 60, graph_from_start=True)[0]


def _blind_turn_run(
    config: LocaliserConfig, seed: int, glitch: int | None = None, blind_frames: int = 30
) -> list[str]:
    """A robot along the circle, its graph pose at the truth while it sees landmarks.
    For `blind_frames` frames from frame 40 it sees none while it turns (30 frames: 1.5
    rad) and its odometry turns 33 % too far (as MRCLAM-6 robot 2's once did), so the
    graph's pose, dead reckoning, drifts (~28 deg in 30 frames); when bearings return the
    graph corrects back to the truth over five frames, as a graph does. The robot was
    never moved. At frame `glitch` the graph's pose is 0.5 m and 0.5 rad off for that
    frame alone, so it does not explain the frame's bearings. The statuses."""
    loc = Localiser(config)
    rng, world = np.random.default_rng(seed), np.random.default_rng(seed + 1)
    statuses: list[str] = []
    previous = graph = None
    back = 40 + blind_frames
    for k in range(back + 40):
        truth = _circle_pose(k)
        blind = 40 <= k < back
        odo = None
        if previous is not None:
            odo = _odometry(previous, truth)
            if blind:
                odo[2] *= 1.33
        if blind and graph is not None and odo is not None:
            graph = _dead_reckon(graph, odo)
        elif graph is not None and k >= back:
            graph = graph + (truth - graph) * min(1.0, (k - back + 1) / 5.0)
        else:
            graph = truth.copy()
        labels, z = ([], []) if blind else _frame(truth, world)
        shown = graph if k != glitch else graph + np.array([0.5, 0.0, 0.5])
        result = _step(loc, k, odo, labels, z, shown, rng)
        statuses.append(result.status)
        previous = truth
    return statuses


def test_the_graph_correcting_a_blind_turn_is_no_kidnap() -> None:
    """Odometry drifts most while turning; a graph with no bearing follows that drift
    and corrects it when bearings return. The old-pose test allows the turn made blind
    before its old pose (kidnap_blind_turn_sigma): no `lost`. Without that allowance the
    same run is lost."""
    config = LocaliserConfig(lost_frames=10_000)
    assert config.kidnap_blind_turn_sigma > 0
    for seed in range(2):
        assert LOST not in _blind_turn_run(config, seed)
    strict = LocaliserConfig(lost_frames=10_000, kidnap_blind_turn_sigma=0.0)
    assert any(LOST in _blind_turn_run(strict, seed) for seed in range(2))


def test_a_blind_turn_after_the_old_pose_is_no_kidnap() -> None:
    """A glitch of the graph's pose just before a long blind turn (60 frames, 3 rad)
    makes it suspect; by the time bearings return the suspicion is older than
    kidnap_window, so the old pose has slid on into the turn, half its drift made. It
    is allowed the turn made blind around it up to the first bearing, not the (zero)
    turn before the glitch: no `lost`. Without the allowance the same run is lost."""
    config = LocaliserConfig(lost_frames=10_000)
    glitch, blind = 35, 60
    assert 40 + blind - glitch > config.kidnap_window
    for seed in range(2):
        assert LOST not in _blind_turn_run(config, seed, glitch, blind)
    strict = LocaliserConfig(lost_frames=10_000, kidnap_blind_turn_sigma=0.0)
    assert any(LOST in _blind_turn_run(strict, seed, glitch, blind) for seed in range(2))


def test_a_held_check_relocalises_once_its_solution_has_held() -> None:
    """WindowCheckConfig.stable_frames: on a map without errors the check's solution
    holds, so the robot is relocalised that many frames after the check first confirmed
    it, as close to the truth."""
    first = _kidnap_run(Localiser(), None, graph_from_start=False)
    held = LocaliserConfig(window_check=WindowCheckConfig(stable_frames=6))
    later = _kidnap_run(Localiser(held), None, graph_from_start=False)
    k0, k1 = first[0].index(RELOCALISED), later[0].index(RELOCALISED)
    assert k1 >= k0 + 6
    assert later[1][0][1] < 0.3


def test_a_solution_that_moves_waits_again() -> None:
    """A solution that moved beyond stable_tolerance since it was first confirmed
    (beyond what the odometry since explains) starts the wait again from the newer
    one; one that held is confirmed."""
    config = LocaliserConfig(window_check=WindowCheckConfig(stable_frames=3))
    step = WindowFrame(np.array([0.1, 0.0, 0.0]), 0.2, np.zeros((0, 2)), np.zeros(0), np.zeros(0))
    frames = [step] * 10
    track = RobotTrack(pf=None, status=INITIALISING)  # type: ignore[arg-type]
    start = np.array([1.0, 2.0, 0.0])
    assert _held(track, start, frames[:4], 3, config) == WAIT
    assert (
        _held(track, start + np.array([0.2, 0.0, 0.0]), frames[:6], 3, config) == WAIT
    )  # too soon
    moved = start + np.array([0.3 + 0.5, 0.0, 0.0])  # three steps of 0.1 m explain 0.3 of it
    assert _held(track, moved, frames[:7], 3, config) == WAIT
    assert track.held is not None and track.held[1] == 7
    assert _held(track, moved + np.array([0.32, 0.0, 0.01]), frames[:10], 3, config) == CONFIRMED
    assert track.held is None
