"""Particle filter: sensor-model convention, resampling invariants, determinism, recovery."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from graph.angles import wrap_angle, wrap_angles
from graph.particles import (
    FilterConfig,
    ParticleFilter,
    bearing_log_likelihood,
    effective_sample_size,
    kld_particle_count,
    multinomial_resample,
    normalise_log_weights,
    predicted_bearings,
    systematic_resample,
    uniform_injector,
)

SIGMA = math.radians(3.0)
EPS = 0.1


def _density(d: float) -> float:
    gauss = (1 - EPS) * math.exp(-0.5 * (d / SIGMA) ** 2) / (math.sqrt(2 * math.pi) * SIGMA)
    return EPS / (2 * math.pi) + gauss


def _loglik(particles: np.ndarray, lm: np.ndarray, z: np.ndarray, q: np.ndarray) -> np.ndarray:
    return bearing_log_likelihood(particles, lm, z, q, sigma_rad=SIGMA, outlier_fraction=EPS)


def test_convention_predicted_bearing_is_ccw_from_heading() -> None:
    # Robot at the origin facing +y: a landmark at (-1, 1) is 45 deg to its left.
    p = np.array([[0.0, 0.0, math.pi / 2]])
    lm = np.array([[-1.0, 1.0], [1.0, 1.0], [0.0, -1.0]])
    got = predicted_bearings(p, lm)[0]
    np.testing.assert_allclose(got, [math.pi / 4, -math.pi / 4, math.pi], atol=1e-6)


def test_convention_sensor_model_golden_values() -> None:
    p = np.array([[1.0, 2.0, 0.3]])
    lm = np.array([[4.0, 6.0]])
    truth = wrap_angle(math.atan2(4.0, 3.0) - 0.3)
    for d in (0.0, 0.02, -0.05, 1.0, math.pi - 0.01):
        z = np.array([wrap_angle(truth + d)])
        got = _loglik(p, lm, z, np.ones(1))[0]
        assert got == pytest.approx(math.log(_density(d)), abs=1e-4)


def test_sensor_model_wraps_around_pi() -> None:
    # The landmark is almost straight behind: predicted bearing ~ +pi - 0.001.
    p = np.array([[0.0, 0.0, 0.0]])
    lm = np.array([[-10.0, 0.01]])
    across = _loglik(p, lm, np.array([-math.pi + 0.001]), np.ones(1))[0]  # d = 0.002 across pi
    same_side = _loglik(p, lm, np.array([math.pi - 0.003]), np.ones(1))[0]  # d = 0.002
    assert across == pytest.approx(same_side, abs=1e-4)
    assert across == pytest.approx(math.log(_density(0.002)), abs=1e-3)


def test_sensor_model_quality_scales_each_landmark() -> None:
    p = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.1]])
    lm = np.array([[3.0, 1.0], [-2.0, 2.0]])
    z = np.array([0.5, 2.0])
    both = _loglik(p, lm, z, np.array([1.0, 1.0]))
    first = _loglik(p, lm[:1], z[:1], np.ones(1))
    half = _loglik(p, lm, z, np.array([1.0, 0.5]))
    ignored = _loglik(p, lm, z, np.array([1.0, 0.0]))
    np.testing.assert_allclose(ignored, first, rtol=1e-5)
    np.testing.assert_allclose(half, first + 0.5 * (both - first), rtol=1e-5)


def _loglik_reference(particles, lm, z, q) -> np.ndarray:
    """The sensor model written plainly in float64: wrapped differences, density, sum."""
    rel = lm[None, :, :] - particles[:, None, :2]
    predicted = np.arctan2(rel[..., 1], rel[..., 0]) - particles[:, 2:3]
    d = wrap_angles(z[None, :] - predicted)
    gauss = (1 - EPS) * np.exp(-0.5 * (d / SIGMA) ** 2) / (math.sqrt(2 * math.pi) * SIGMA)
    return np.log(EPS / (2 * math.pi) + gauss) @ q


@pytest.mark.parametrize("offset", [0.0, 3.0e5])
@pytest.mark.parametrize("n", [7, 1000, 2500])
def test_sensor_model_agrees_with_the_plain_formula(n: int, offset: float) -> None:
    """The factored float32 path (blocks of particles) against float64, also far from the
    origin (UTM-sized coordinates); half the bearings near their predicted values."""
    rng = np.random.default_rng(n)
    particles = np.column_stack(
        [rng.uniform(0, 10, n) + offset, rng.uniform(0, 10, n) - offset, rng.uniform(-4, 4, n)]
    )
    shift = np.array([offset, -offset])
    lm = rng.uniform(-5, 15, (32, 2)) + shift
    z = rng.uniform(-math.pi, math.pi, 32)
    first = particles[:1] - np.append(shift, 0.0)
    z[:16] = wrap_angles(predicted_bearings(first, lm[:16] - shift)[0] + rng.normal(0, SIGMA, 16))
    q = rng.uniform(0, 1, 32)
    got = _loglik(particles, lm, z, q)
    want = _loglik_reference(particles, lm, z, q)
    assert got.shape == (n,) and got.dtype == np.float64
    np.testing.assert_allclose(got, want, atol=1e-3, rtol=1e-5)


weights_st = st.lists(st.floats(0.0, 1.0), min_size=1, max_size=60).filter(lambda w: sum(w) > 0)


@settings(max_examples=60, deadline=None)
@given(weights_st, st.integers(1, 400), st.integers(0, 2**32 - 1))
def test_systematic_resampling_counts_are_floor_or_ceil(
    raw: list[float], n: int, seed: int
) -> None:
    w = np.asarray(raw) / np.sum(raw)
    idx = systematic_resample(w, n, np.random.default_rng(seed))
    assert idx.shape == (n,)
    assert idx.min() >= 0 and idx.max() < len(w)
    counts = np.bincount(idx, minlength=len(w))
    assert counts.sum() == n
    assert np.all(counts >= np.floor(n * w - 1e-9)) and np.all(counts <= np.ceil(n * w + 1e-9))
    assert np.all(counts[w == 0] == 0)


@settings(max_examples=40, deadline=None)
@given(weights_st, st.integers(1, 400), st.integers(0, 2**32 - 1))
def test_multinomial_resampling_stays_on_support(raw: list[float], n: int, seed: int) -> None:
    w = np.asarray(raw) / np.sum(raw)
    idx = multinomial_resample(w, n, np.random.default_rng(seed))
    assert idx.shape == (n,)
    assert np.all(w[idx] > 0)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-700.0, 50.0), min_size=1, max_size=100))
def test_log_weights_normalise_and_ess_bounds(raw: list[float]) -> None:
    lw = normalise_log_weights(np.asarray(raw))
    assert np.exp(lw).sum() == pytest.approx(1.0, rel=1e-9)
    ess = effective_sample_size(np.asarray(raw))
    assert 1.0 - 1e-9 <= ess <= len(raw) + 1e-9


def test_kld_bound_grows_with_occupied_bins() -> None:
    k = np.arange(1, 500)
    n = np.asarray(kld_particle_count(k, epsilon=0.05, z_quantile=2.326))
    assert np.all(np.diff(n) >= 0)
    assert n[-1] > 5000 > n[10]


def test_kld_size_small_when_concentrated_large_when_spread() -> None:
    rng = np.random.default_rng(3)
    cfg = FilterConfig()
    tight = ParticleFilter.around(np.zeros(3), (0.02, 0.02, 0.01), cfg, rng=rng, n=3000)
    assert tight.kld_size(np.exp(tight.log_weights), rng=rng) == cfg.min_particles
    spread = ParticleFilter.from_poses(uniform_injector((0, 0, 8, 8))(3000, rng), cfg)
    assert spread.kld_size(np.exp(spread.log_weights), rng=rng) >= 4000


def test_convention_predict_moves_in_the_robot_frame() -> None:
    cfg = FilterConfig(
        motion_sigma_floor=(1e-6, 1e-6, 1e-6),
        motion_sigma_per_metre=(0.0, 0.0, 0.0),
        motion_sigma_per_radian=0.0,
        motion_sigma_per_sqrt_second=(0.0, 0.0, 0.0),
    )
    pf = ParticleFilter.from_poses(np.array([[1.0, 1.0, math.pi / 2]] * 10), cfg)
    pf.predict(np.array([1.0, 0.5, 0.2]), dt_s=0.1, rng=np.random.default_rng(0))
    np.testing.assert_allclose(pf.particles[:, 0], 0.5, atol=1e-4)
    np.testing.assert_allclose(pf.particles[:, 1], 2.0, atol=1e-4)
    np.testing.assert_allclose(pf.particles[:, 2], math.pi / 2 + 0.2, atol=1e-4)


# --------------------------------------------------------------------------- a small world
LANDMARKS = np.array(
    [[0.0, 0.0], [6.0, 0.0], [6.0, 6.0], [0.0, 6.0], [3.0, -1.0], [7.0, 3.0], [3.0, 7.0],
     [-1.0, 3.0], [1.5, 4.5], [4.5, 1.5]]
)  # fmt: skip
BOUNDS = (-1.0, -1.0, 7.0, 7.0)


def _circle_pose(k: int, centre: tuple[float, float] = (3.0, 3.0)) -> np.ndarray:
    a = 0.05 * k
    return np.array([centre[0] + 1.5 * math.cos(a), centre[1] + 1.5 * math.sin(a), a + math.pi / 2])


def _observe(pose: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    z = predicted_bearings(pose[None, :], LANDMARKS)[0].astype(np.float64)
    z = wrap_angles(z + rng.normal(0.0, math.radians(1.0), len(z)))
    fov = np.abs(z) < 1.2  # a forward-looking sensor, like MRCLAM's camera
    return LANDMARKS[fov], z[fov]


def _odometry(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    c, s = math.cos(a[2]), math.sin(a[2])
    d = b[:2] - a[:2]
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], wrap_angle(b[2] - a[2])])


def _run(seed: int, frames: int, kidnap_at: int | None = None) -> tuple[ParticleFilter, list]:
    rng = np.random.default_rng(seed)
    world = np.random.default_rng(seed + 1000)
    cfg = FilterConfig()
    inject = uniform_injector(BOUNDS)
    pf = ParticleFilter.from_poses(inject(cfg.max_particles, rng), cfg)
    history = []
    for k in range(frames):
        truth = (
            _circle_pose(k)
            if kidnap_at is None or k < kidnap_at
            else _circle_pose(k, centre=(3.0, 4.0)) + np.array([0.0, 0.0, 0.0])
        )
        if k > 0:
            previous = history[-1][0]
            odo = (
                _odometry(previous, truth)
                if k != kidnap_at
                else _odometry(previous, _circle_pose(k))
            )
            pf.predict(odo, dt_s=0.2, rng=rng)
        lm, z = _observe(truth, world)
        pf.update(lm, z, rng=rng, injector=inject)
        history.append((truth, pf.estimate()))
    return pf, history


def _error(truth: np.ndarray, est: np.ndarray) -> tuple[float, float]:
    return float(np.hypot(*(truth[:2] - est[:2]))), abs(wrap_angle(float(truth[2] - est[2])))


def test_global_localisation_converges_on_a_synthetic_world() -> None:
    pf, history = _run(seed=5, frames=40)
    truth, est = history[-1]
    dist, yaw = _error(truth, est.pose_xytheta)
    assert est.converged
    assert dist < 0.2 and yaw < math.radians(5)
    assert pf.size < 1000  # KLD shrank the set once converged


def test_same_seed_same_particles() -> None:
    a, _ = _run(seed=11, frames=8)
    b, _ = _run(seed=11, frames=8)
    c, _ = _run(seed=12, frames=8)
    np.testing.assert_array_equal(a.particles, b.particles)
    np.testing.assert_array_equal(a.log_weights, b.log_weights)
    assert a.particles.shape != c.particles.shape or not np.array_equal(a.particles, c.particles)


def test_recovers_after_a_kidnap() -> None:
    kidnap = 40
    _, history = _run(seed=7, frames=kidnap + 60, kidnap_at=kidnap)
    before = _error(history[kidnap - 1][0], history[kidnap - 1][1].pose_xytheta)
    assert before[0] < 0.2
    just_after = _error(history[kidnap][0], history[kidnap][1].pose_xytheta)
    assert just_after[0] > 0.5  # the kidnap (1 m) really displaced the robot
    recovered = [
        k
        for k in range(kidnap, len(history))
        if _error(history[k][0], history[k][1].pose_xytheta)[0] < 0.2 and history[k][1].converged
    ]
    assert recovered, "the filter never recovered"
    assert recovered[0] - kidnap <= 25
    dist, yaw = _error(history[-1][0], history[-1][1].pose_xytheta)
    assert dist < 0.2 and yaw < math.radians(5)


def test_injected_particles_count_in_the_estimate_only_once_an_observation_weighed_them() -> None:
    """A tight belief that a resampling topped up with 30 % injected poses is converged:
    the injected poses are the search's proposals until an observation weighs them."""
    rng = np.random.default_rng(3)
    truth = np.array([3.0, 2.5, 0.4])
    cloud = truth + rng.normal(0.0, [0.02, 0.02, math.radians(1.0)], (1000, 3))
    pf = ParticleFilter.from_poses(cloud, FilterConfig(max_particles=1000))
    assert pf.estimate().converged
    pf.resample(rng=rng, injector=uniform_injector((0.0, 0.0, 6.0, 5.0)), inject_fraction=0.3)
    assert pf.unweighed == pf.last_injected == 300
    est = pf.estimate()
    assert est.converged and est.core_weight == pytest.approx(1.0)
    np.testing.assert_allclose(est.pose_xytheta[:2], truth[:2], atol=0.01)
    # Counted with their uniform share (as before), the core held 70 % of the weight.
    counted = dataclasses.replace(pf, unweighed=0).estimate()
    assert not counted.converged and counted.core_weight == pytest.approx(0.7, abs=0.02)
    # An observation weighs them all: none is left out any more.
    z = predicted_bearings(truth[None, :], LANDMARKS)[0].astype(np.float64)
    pf.update(LANDMARKS, z, rng=rng)
    assert pf.unweighed == 0
    assert pf.estimate().converged


# --------------------------------------------------------------------------- sharp updates
def _sparse_cloud_and_sharp_fix(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """300 particles spread ~0.7 m / 10 deg around the truth; every landmark seen at once
    with 0.3 deg noise: the likelihood's peak is far narrower than the particle spacing."""
    rng = np.random.default_rng(seed)
    truth = np.array([3.0, 2.5, 0.4])
    cloud = truth + rng.normal(0.0, [0.7, 0.7, math.radians(10.0)], (300, 3))
    z = predicted_bearings(truth[None, :], LANDMARKS)[0].astype(np.float64)
    return truth, cloud, wrap_angles(z + rng.normal(0.0, math.radians(0.3), len(z)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_progressive_correction_draws_particles_to_a_sharp_peak(seed: int) -> None:
    truth, cloud, z = _sparse_cloud_and_sharp_fix(seed)
    sigmas = np.full(len(z), math.radians(0.3))
    errors = {}
    for tempering in (0.0, 0.1):
        cfg = FilterConfig(min_particles=300, tempering_ess_fraction=tempering)
        pf = ParticleFilter.from_poses(cloud, cfg)
        pf.update(LANDMARKS, z, rng=np.random.default_rng(seed), sigmas_rad=sigmas)
        est = pf.estimate()
        errors[tempering] = _error(truth, est.pose_xytheta)[0]
        if tempering:
            assert pf.last_stages > 1
            assert errors[tempering] < 0.05, "the peak is found, not just the nearest particle"
        else:
            assert pf.last_stages == 1
    nearest = float(np.min(np.hypot(*(cloud[:, :2] - truth[:2]).T)))
    assert errors[0.1] < errors[0.0] and errors[0.1] < nearest


def test_each_observation_sigma_shapes_its_likelihood() -> None:
    cfg = FilterConfig(bearing_sigma_floor_rad=math.radians(0.5))
    pf = ParticleFilter.from_poses(np.zeros((1, 3)), cfg)
    got = pf.bearing_sigmas(3, np.array([math.radians(1.0), np.nan, math.radians(4.0)]))
    want = np.hypot(np.radians([1.0, 1.5, 4.0]), math.radians(0.5))  # NaN: the default
    np.testing.assert_allclose(got, want)
    p = np.array([[0.0, 0.0, 0.0]])
    lm = np.array([[5.0, 0.0], [5.0, 0.0]])
    off = np.array([math.radians(3.0)] * 2)
    per = bearing_log_likelihood(
        p, lm, off, np.array([1.0, 0.0]), sigma_rad=np.radians([1.0, 4.0]), outlier_fraction=EPS
    )
    wide = bearing_log_likelihood(
        p, lm, off, np.array([0.0, 1.0]), sigma_rad=np.radians([1.0, 4.0]), outlier_fraction=EPS
    )
    assert wide[0] > per[0]  # 3 deg off: 3 sigma for the sharp one, 0.75 for the wide one


def test_a_config_pickled_before_new_fields_unpickles_with_defaults() -> None:
    cfg = FilterConfig(min_particles=123)
    state = cfg.__getstate__()
    old = FilterConfig.__new__(FilterConfig)
    old.__setstate__(tuple(state)[:-3])  # as pickled before the last three fields existed
    assert old.min_particles == 123
    assert old.tempering_ess_fraction == FilterConfig().tempering_ess_fraction
    assert old.bearing_sigma_floor_rad == FilterConfig().bearing_sigma_floor_rad


@pytest.mark.parametrize(
    "bad",
    [
        {"tempering_ess_fraction": 1.0},
        {"tempering_ess_fraction": -0.1},
        {"tempering_max_stages": 0},
        {"bearing_sigma_floor_rad": -0.01},
        {"bearing_sigma_rad": 0.0},
    ],
)
def test_config_refuses_unsafe_values(bad: dict) -> None:
    with pytest.raises(ValueError):
        FilterConfig(**bad)
