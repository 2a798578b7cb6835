"""Condensation particle filter over planar poses (x, y, theta) in the map frame.

After Thompson & Zelinsky's local positioning (DESIGN.md, "Place localiser"), with
the recovery their filter lacked:

- particles are an ``(N, 3)`` array ``[x m, y m, theta rad]``; weights are kept as
  log-weights normalised so that ``logsumexp(log_weights) == 0``;
- motion: the odometry ``(dx, dy, dtheta)`` (previous robot frame) is perturbed per
  particle with noise that grows with the motion and the elapsed time;
- sensor model: for each observed landmark j with map position ``l_j``, bearing
  ``z_j`` and match quality ``q_j`` in [0, 1], the wrapped difference
  ``d = wrap(z_j - bearing(x, l_j))`` has density
  ``p(d) = eps / 2pi + (1 - eps) N(d; 0, sigma)`` (uniform outliers + Gaussian);
  a landmark enters the log-likelihood as ``q_j * log p(d)`` (a tempered
  likelihood: a poor match counts for less); sigma is each observation's own (with
  an optional floor in quadrature), or a configured default;
- progressive correction: an observation that would drop the ESS below
  ``tempering_ess_fraction * N`` is applied in tempered stages with resampling and a
  regularisation kernel between them (see ParticleFilter._temper);
- resampling: systematic (or multinomial, by name) when the effective sample size
  falls below ``resample_ess_fraction * N``; the new count is KLD-adaptive (Fox
  2003) within ``[min_particles, max_particles]``;
- augmented MCL (Thrun et al.): slow and fast running averages of the mean
  per-landmark likelihood; when the fast one drops below ``injection_ratio`` times
  the slow one, a fraction ``1 - w_fast / (injection_ratio * w_slow)`` of the
  particles is replaced by draws from an injection proposal (the caller passes one
  drawing around the best-ranked places).

Every stochastic step takes the ``rng`` given to the filter. No Python loop runs
per particle or per landmark.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from graph.angles import TWO_PI, wrap_angles
from graph.types import restore_fields

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
Injector = Callable[[int, np.random.Generator], FloatArray]
"""Draws ``n`` poses ``(n, 3)`` for injection or initialisation."""


# --------------------------------------------------------------------------- resampling
def systematic_resample(weights: FloatArray, n: int, rng: np.random.Generator) -> IntArray:
    """Indices ``(n,)`` into ``weights`` (normalised, shape ``(N,)``): one uniform offset,
    ``n`` evenly spaced pointers. Each index i appears floor or ceil of ``n * w_i`` times."""
    positions = (rng.random() + np.arange(n)) / n
    cumulative = np.cumsum(weights)
    cumulative[-1] = 1.0  # guard against rounding below the last pointer
    return np.searchsorted(cumulative, positions, side="right").astype(np.int64)


def multinomial_resample(weights: FloatArray, n: int, rng: np.random.Generator) -> IntArray:
    """Indices ``(n,)`` drawn independently with probabilities ``weights``."""
    cumulative = np.cumsum(weights)
    cumulative[-1] = 1.0
    return np.searchsorted(cumulative, rng.random(n), side="right").astype(np.int64)


RESAMPLERS: dict[str, Callable[[FloatArray, int, np.random.Generator], IntArray]] = {
    "systematic": systematic_resample,
    "multinomial": multinomial_resample,
}


def normalise_log_weights(log_weights: FloatArray) -> FloatArray:
    """Shift log-weights so that they sum (in linear space) to one."""
    peak = float(np.max(log_weights))
    return log_weights - (peak + math.log(float(np.sum(np.exp(log_weights - peak)))))


def _ess(log_weights: FloatArray) -> float:
    """ESS of unnormalised log-weights (see effective_sample_size)."""
    w = np.exp(log_weights - np.max(log_weights))
    return float(w.sum() ** 2 / (w @ w))


def effective_sample_size(log_weights: FloatArray) -> float:
    """``1 / sum(w^2)`` of normalised weights: N for uniform weights, 1 for a single one."""
    w = np.exp(normalise_log_weights(log_weights))
    return float(1.0 / np.sum(w * w))


def kld_particle_count(
    k_bins: IntArray | int, *, epsilon: float, z_quantile: float
) -> IntArray | int:
    """Fox's KLD bound: particles needed so that the KL divergence between the sample
    and a histogram over ``k_bins`` occupied bins stays below ``epsilon`` with
    probability given by the standard-normal quantile ``z_quantile`` (Wilson-Hilferty)."""
    k = np.maximum(np.asarray(k_bins, dtype=np.float64) - 1.0, 1.0)
    a = 2.0 / (9.0 * k)
    n = k / (2.0 * epsilon) * (1.0 - a + np.sqrt(a) * z_quantile) ** 3
    out = np.ceil(n).astype(np.int64)
    return int(out) if np.ndim(out) == 0 else out


# --------------------------------------------------------------------------- sensor model
_CHUNK = 1024
"""Particles per block of the sensor model: keeps the (block, 2M) float32 work arrays in
cache (5000 x 32 in one go ran ~15x slower than 1000 x 32, not 5x)."""


def predicted_bearings(particles: FloatArray, landmarks_xy: FloatArray) -> NDArray[np.float32]:
    """``(N, M)`` bearings (robot frame, CCW from +x, wrapped) from each particle
    ``(N, 3)`` to each landmark ``(M, 2)``; float32 (the filter's hot path)."""
    p = particles.astype(np.float32)
    lm = np.asarray(landmarks_xy, dtype=np.float32)
    dx = lm[None, :, 0] - p[:, 0:1]
    dy = lm[None, :, 1] - p[:, 1:2]
    return wrap_angles(np.arctan2(dy, dx) - p[:, 2:3]).astype(np.float32)


def _ray_factors(
    particles: FloatArray, landmarks_xy: FloatArray, bearings_rad: FloatArray
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Factors ``F (N, 4)`` and ``W (4, 2M)`` with ``F @ W = [along | across]``: the ray
    from particle i to landmark j in the frame of the direction particle i would observe
    landmark j in (heading ``theta_i + z_j``), so that ``atan2(across, along)`` is the
    wrapped bearing error.

    With ``(dx, dy) = l_j - p_i`` and ``phi = theta_i + z_j``,
    ``along = dx cos(phi) + dy sin(phi)`` and ``across = dy cos(phi) - dx sin(phi)``;
    expanding ``cos(phi)``, ``sin(phi)`` separates them into sums of (per-particle) x
    (per-landmark) products: F = [c, s, x c + y s, x s - y c] (c, s of theta_i) and
    W's columns [lx cz + ly sz, ly cz - lx sz, -cz, sz] (along) and
    [ly cz - lx sz, -(lx cz + ly sz), sz, cz] (across). One small GEMM replaces four
    broadcast passes. Coordinates are taken relative to the landmarks' mean (in
    float64) before the float32 cast, so that large map coordinates keep precision.
    """
    lm = np.asarray(landmarks_xy, dtype=np.float64)
    origin = lm.mean(axis=0)
    lx, ly = lm[:, 0] - origin[0], lm[:, 1] - origin[1]
    z = np.asarray(bearings_rad, dtype=np.float64)
    cz, sz = np.cos(z), np.sin(z)
    a, b = lx * cz + ly * sz, ly * cz - lx * sz
    m = len(z)
    w = np.empty((4, 2 * m), dtype=np.float32)
    w[0, :m], w[1, :m], w[2, :m], w[3, :m] = a, b, -cz, sz
    w[0, m:], w[1, m:], w[2, m:], w[3, m:] = b, -a, sz, cz
    theta = particles[:, 2]
    c, s = np.cos(theta), np.sin(theta)
    x, y = particles[:, 0] - origin[0], particles[:, 1] - origin[1]
    f = np.empty((4, len(particles)), dtype=np.float32)
    f[0], f[1], f[2], f[3] = c, s, x * c + y * s, x * s - y * c
    return f.T, w


def bearing_log_likelihood(
    particles: FloatArray,
    landmarks_xy: FloatArray,
    bearings_rad: FloatArray,
    quality: FloatArray,
    *,
    sigma_rad: float | FloatArray,
    outlier_fraction: float,
) -> FloatArray:
    """``(N,)`` log-likelihood of the observed bearings for each particle.

    Convention: ``d = wrap(z - (atan2(ly - y, lx - x) - theta))``; the density of d
    is ``eps / 2pi + (1 - eps) exp(-d^2 / 2 sigma^2) / (sqrt(2pi) sigma)``, and each
    landmark's log-density is multiplied by its match quality in [0, 1]. ``sigma_rad``
    is one sigma for all landmarks or one per landmark ``(M,)``.

    Computed in float32 (|error| ~1e-4 in the log-likelihood of 32 landmarks), blocks of
    ``_CHUNK`` particles, work arrays allocated once per call (see _ray_factors).
    """
    n, m = particles.shape[0], len(bearings_rad)
    if m == 0:
        return np.zeros(n)
    f, w = _ray_factors(particles, landmarks_xy, bearings_rad)
    q = np.asarray(quality, dtype=np.float32)
    eps = float(outlier_fraction)
    sigma = np.broadcast_to(np.asarray(sigma_rad, dtype=np.float64), (m,))
    scale = (-0.5 / sigma**2).astype(np.float32)
    gauss = ((1.0 - eps) / (math.sqrt(2.0 * math.pi) * sigma)).astype(np.float32)
    floor = np.float32(eps / TWO_PI)
    block = min(n, _CHUNK)
    rays = np.empty((block, 2 * m), dtype=np.float32)
    d = np.empty((block, m), dtype=np.float32)
    out = np.empty(n, dtype=np.float32)
    for i in range(0, n, block):
        k = min(block, n - i)
        r, e = rays[:k], d[:k]
        np.matmul(f[i : i + k], w, out=r)
        np.arctan2(r[:, m:], r[:, :m], out=e)  # wrap(bearing - z): the sign squares away
        np.multiply(e, e, out=e)
        e *= scale
        np.exp(e, out=e)
        e *= gauss
        e += floor
        np.log(e, out=e)
        # A matrix-vector product: numpy's row sum over a short axis is ~10x slower.
        np.matmul(e, q, out=out[i : i + k])
    return out.astype(np.float64)


# --------------------------------------------------------------------------- the filter
@dataclass(frozen=True, slots=True)
class FilterConfig:
    """Parameters of the place localiser's particle filter (SI units, radians)."""

    min_particles: int = 300
    max_particles: int = 5000
    bearing_sigma_rad: float = math.radians(1.5)
    """Gaussian part of the sensor model for an observation that states no sigma of its
    own. (MRCLAM-6 before progressive correction: 1 deg converged sooner but more often
    to wrong poses, 2-3 deg more slowly and less often in 150 frames.)"""
    outlier_fraction: float = 0.1
    """Weight of the uniform part of the sensor model. (MRCLAM-6: 0.25 localised 88 % of 50
    starts against 82 % with 0.1, but while tracking robot 1 in a capped map the filter then
    drifted 2 m off a good graph, which sent the robot 'lost'.)"""
    motion_sigma_floor: tuple[float, float, float] = (0.01, 0.01, math.radians(1.0))
    motion_sigma_per_metre: tuple[float, float, float] = (0.1, 0.1, math.radians(5.0))
    motion_sigma_per_radian: float = 0.1
    motion_sigma_per_sqrt_second: tuple[float, float, float] = (0.01, 0.01, math.radians(2.0))
    resample_ess_fraction: float = 0.5
    resampler: str = "systematic"
    alpha_slow: float = 0.02
    alpha_fast: float = 0.3
    max_injection_fraction: float = 0.5
    injection_ratio: float = 0.6
    """Inject only while w_fast < injection_ratio * w_slow (a fraction 1 - w_fast /
    (injection_ratio * w_slow)); 1.0 is Thrun's rule, which on MRCLAM's uneven
    observations kept injecting during normal tracking."""
    kld_epsilon: float = 0.05
    kld_z_quantile: float = 2.326
    """Upper standard-normal quantile of the KLD bound (2.326: 99 %)."""
    kld_bin: tuple[float, float, float] = (0.25, 0.25, math.radians(10.0))
    converged_sigma_m: float = 0.25
    """Largest position sigma (major axis) of a converged filter."""
    converged_sigma_rad: float = math.radians(8.0)
    converged_weight: float = 0.9
    """Share of the weight the main mode's core must hold for the filter to be converged."""
    mode_cell_m: float = 0.5
    core_radius_m: float = 0.75
    core_angle_rad: float = math.radians(30.0)
    # New fields go last: a pickled config is the tuple of its field values, in order.
    tempering_ess_fraction: float = 0.1
    """Progressive correction: an observation is applied in stages ``L^lambda_k`` (the
    lambdas sum to 1), each the largest that keeps the ESS at or above this share of
    the particles, with resampling and a regularisation kernel between stages. A sharp
    likelihood that falls between the particles then draws them towards its peak
    instead of collapsing the set onto the few nearest. 0 disables (one stage)."""
    tempering_max_stages: int = 6
    bearing_sigma_floor_rad: float = 0.0
    """Added in quadrature to an observation's own sigma: what the sensor's figure leaves
    out (landmark map error, time stamps, the robot's motion during a frame). MRCLAM-6
    (3 x 50 starts, observations stating 1 deg; the bearings' residual at ground truth
    is 0.3-0.6 deg): 0 localised 97 %, 0.5 deg 88 %."""

    def __setstate__(self, state: tuple[Any, ...]) -> None:
        restore_fields(self, state)  # also a state pickled before later fields existed

    def __post_init__(self) -> None:
        if not 1 <= self.min_particles <= self.max_particles:
            raise ValueError("need 1 <= min_particles <= max_particles")
        if not 0.0 <= self.outlier_fraction < 1.0:
            raise ValueError("outlier_fraction must lie in [0, 1)")
        if self.resampler not in RESAMPLERS:
            raise ValueError(f"resampler must be one of {sorted(RESAMPLERS)}")
        if not 0.0 < self.alpha_slow < self.alpha_fast <= 1.0:
            raise ValueError("need 0 < alpha_slow < alpha_fast <= 1")
        if not 0.0 <= self.tempering_ess_fraction < 1.0 or self.tempering_max_stages < 1:
            raise ValueError("need 0 <= tempering_ess_fraction < 1 and tempering_max_stages >= 1")
        if not self.bearing_sigma_floor_rad >= 0.0 or not self.bearing_sigma_rad > 0.0:
            raise ValueError("need bearing_sigma_rad > 0 and bearing_sigma_floor_rad >= 0")


def motion_sigmas(odometry_xytheta: FloatArray, dt_s: float, config: FilterConfig) -> FloatArray:
    """(3,) sigmas (m, m, rad) of the motion model's noise on one odometry increment
    (previous robot frame) taking `dt_s` seconds: floor + per metre + per radian turned,
    in quadrature with the per-sqrt-second term."""
    odo = np.asarray(odometry_xytheta, dtype=np.float64)
    dist = math.hypot(odo[0], odo[1])
    sig = (
        np.asarray(config.motion_sigma_floor)
        + np.asarray(config.motion_sigma_per_metre) * dist
        + np.array([0.0, 0.0, config.motion_sigma_per_radian * abs(odo[2])])
    )
    out: FloatArray = np.hypot(
        sig, np.asarray(config.motion_sigma_per_sqrt_second) * math.sqrt(max(dt_s, 0.0))
    )
    return out


@dataclass(frozen=True, slots=True)
class FilterEstimate:
    """Main-mode mean pose, its ``(3, 3)`` covariance of (x, y, theta), convergence."""

    pose_xytheta: FloatArray
    covariance: FloatArray
    converged: bool
    particles: int
    injected: int
    core_weight: float = 1.0
    """Share of the weight in the main mode's core (see ParticleFilter.estimate)."""


@dataclass
class ParticleFilter:
    """Particles ``(N, 3)`` and their log-weights ``(N,)``; see the module docstring."""

    particles: FloatArray
    log_weights: FloatArray
    config: FilterConfig = field(default_factory=FilterConfig)
    w_slow: float = 0.0
    w_fast: float = 0.0
    last_injected: int = 0
    unweighed: int = 0
    """The last this-many particles were injected and no observation has weighed them
    yet (see `estimate`)."""
    last_stages: int = 1
    """Stages the last update applied its observation in (see _temper)."""

    # ------------------------------------------------------------ construction
    @classmethod
    def from_poses(cls, poses_xytheta: FloatArray, config: FilterConfig) -> ParticleFilter:
        poses = np.array(poses_xytheta, dtype=np.float64, copy=True).reshape(-1, 3)
        poses[:, 2] = wrap_angles(poses[:, 2])
        n = len(poses)
        return cls(poses, np.full(n, -math.log(n)), config)

    @classmethod
    def around(
        cls,
        pose_xytheta: FloatArray,
        sigmas: tuple[float, float, float],
        config: FilterConfig,
        *,
        rng: np.random.Generator,
        n: int | None = None,
    ) -> ParticleFilter:
        """A Gaussian cloud around one pose (e.g. a known initial pose)."""
        count = config.min_particles if n is None else n
        poses = np.asarray(pose_xytheta, dtype=np.float64) + rng.normal(
            0.0, sigmas, size=(count, 3)
        )
        return cls.from_poses(poses, config)

    # ------------------------------------------------------------ steps
    @property
    def size(self) -> int:
        return int(self.particles.shape[0])

    def predict(
        self, odometry_xytheta: FloatArray, *, dt_s: float, rng: np.random.Generator
    ) -> None:
        """Move every particle by the odometry (previous robot frame) plus noise."""
        odo = np.asarray(odometry_xytheta, dtype=np.float64)
        sig = motion_sigmas(odo, dt_s, self.config)
        noisy = odo[None, :] + rng.normal(0.0, 1.0, size=(self.size, 3)) * sig[None, :]
        c, s = np.cos(self.particles[:, 2]), np.sin(self.particles[:, 2])
        self.particles[:, 0] += c * noisy[:, 0] - s * noisy[:, 1]
        self.particles[:, 1] += s * noisy[:, 0] + c * noisy[:, 1]
        self.particles[:, 2] = wrap_angles(self.particles[:, 2] + noisy[:, 2])

    def update(
        self,
        landmarks_xy: FloatArray,
        bearings_rad: FloatArray,
        quality: FloatArray | None = None,
        *,
        rng: np.random.Generator,
        injector: Injector | None = None,
        sigmas_rad: FloatArray | None = None,
    ) -> None:
        """Weight by the observed bearings ``(M,)`` to landmarks ``(M, 2)``; then augmented
        MCL bookkeeping, resampling (KLD-sized) when the ESS is low, and injection.
        ``sigmas_rad`` ``(M,)``: each observation's own sigma (NaN: none stated)."""
        cfg = self.config
        self.last_injected = 0
        if len(bearings_rad) == 0:
            return
        lm, z, q, sigma = self._observations(landmarks_xy, bearings_rad, quality, sigmas_rad)

        def likelihood(particles: FloatArray) -> FloatArray:
            return bearing_log_likelihood(
                particles,
                lm,
                z,
                q,
                sigma_rad=sigma,
                outlier_fraction=cfg.outlier_fraction,
            )

        loglik = likelihood(self.particles)
        q_sum = float(q.sum())
        if q_sum > 0:
            # sum_i w_i exp((loglik_i - sum_j q_j peak_j) / q_sum), in one pass
            per_landmark = self._per_landmark_log(loglik, q, sigma)
            per_landmark += self.log_weights
            w_avg = float(np.exp(per_landmark, out=per_landmark).sum())
            if self.w_slow == 0.0:
                self.w_slow = self.w_fast = w_avg
            else:
                self.w_slow += cfg.alpha_slow * (w_avg - self.w_slow)
                self.w_fast += cfg.alpha_fast * (w_avg - self.w_fast)
        self.last_stages = 1
        if cfg.tempering_ess_fraction > 0:
            loglik = self._temper(loglik, likelihood, rng=rng)
        self.log_weights = normalise_log_weights(self.log_weights + loglik)
        self.unweighed = 0
        inject = 0.0
        if injector is not None and self.w_slow > 0:
            ratio = self.w_fast / (cfg.injection_ratio * self.w_slow)
            inject = min(cfg.max_injection_fraction, max(0.0, 1.0 - ratio))
        w = np.exp(self.log_weights)
        if inject > 0.0 or 1.0 / float(w @ w) < cfg.resample_ess_fraction * self.size:
            self.resample(rng=rng, injector=injector, inject_fraction=inject)

    def _per_landmark_log(self, loglik: FloatArray, q: FloatArray, sigma: FloatArray) -> FloatArray:
        """Log of the mean per-landmark likelihood relative to its peak (in (0, 1] once
        exponentiated; comparable between frames that see different numbers of
        landmarks), for log-likelihoods ``(N,)`` of observations of quality q."""
        cfg = self.config
        peaks = np.log(
            cfg.outlier_fraction / TWO_PI
            + (1.0 - cfg.outlier_fraction) / (math.sqrt(TWO_PI) * sigma)
        )
        return np.asarray((loglik - float(q @ peaks)) / float(q.sum()))

    def fit(
        self,
        pose_xytheta: FloatArray,
        landmarks_xy: FloatArray,
        bearings_rad: FloatArray,
        quality: FloatArray | None = None,
        *,
        sigmas_rad: FloatArray | None = None,
    ) -> float:
        """How well one pose ``(3,)`` explains the observed bearings: the mean
        per-landmark likelihood relative to its peak, the quantity whose weighted
        average over the particles `w_fast` and `w_slow` follow. 1.0 if nothing was
        observed."""
        lm, z, q, sigma = self._observations(landmarks_xy, bearings_rad, quality, sigmas_rad)
        if len(z) == 0 or float(q.sum()) <= 0:
            return 1.0
        loglik = bearing_log_likelihood(
            np.asarray(pose_xytheta, dtype=np.float64).reshape(1, 3),
            lm,
            z,
            q,
            sigma_rad=sigma,
            outlier_fraction=self.config.outlier_fraction,
        )
        return float(np.exp(self._per_landmark_log(loglik, q, sigma))[0])

    def _observations(
        self,
        landmarks_xy: FloatArray,
        bearings_rad: FloatArray,
        quality: FloatArray | None,
        sigmas_rad: FloatArray | None,
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Landmarks ``(M, 2)``, bearings ``(M,)``, qualities clipped to [0, 1] (1 if not
        given) and sensor-model sigmas ``(M,)``, as the sensor model takes them."""
        m = len(bearings_rad)
        q = np.ones(m) if quality is None else np.clip(np.asarray(quality, np.float64), 0, 1)
        return (
            np.asarray(landmarks_xy, dtype=np.float64).reshape(-1, 2),
            np.asarray(bearings_rad, dtype=np.float64),
            q,
            self.bearing_sigmas(m, sigmas_rad),
        )

    def bearing_sigmas(self, m: int, sigmas_rad: FloatArray | None = None) -> FloatArray:
        """``(m,)`` sensor-model sigmas: each observation's own sigma (NaN or None: the
        configured default) with the configured floor added in quadrature."""
        cfg = self.config
        own = np.full(m, np.nan) if sigmas_rad is None else np.asarray(sigmas_rad, np.float64)
        own = np.where(np.isfinite(own) & (own > 0), own, cfg.bearing_sigma_rad)
        return np.asarray(np.hypot(own, cfg.bearing_sigma_floor_rad))

    def _temper(
        self,
        loglik: FloatArray,
        likelihood: Callable[[FloatArray], FloatArray],
        *,
        rng: np.random.Generator,
    ) -> FloatArray:
        """Progressive correction (Oudjane & Musso 2000; adaptive tempering): apply
        ``loglik`` in stages while the whole of it would drop the ESS below
        ``tempering_ess_fraction * N``. Each stage takes the largest exponent that keeps
        the ESS there (bisection), resamples and moves the particles by a Gaussian kernel
        (Silverman's bandwidth times the stage's weighted covariance: the regularised
        particle filter), then re-evaluates the likelihood. Returns the log-likelihood
        share still to apply to the (possibly new) particles."""
        cfg = self.config
        remaining = 1.0
        for _ in range(cfg.tempering_max_stages - 1):
            target = cfg.tempering_ess_fraction * self.size
            if _ess(self.log_weights + remaining * loglik) >= target:
                break
            lo, hi = 0.0, remaining
            for _ in range(12):
                mid = 0.5 * (lo + hi)
                if _ess(self.log_weights + mid * loglik) >= target:
                    lo = mid
                else:
                    hi = mid
            step = max(lo, remaining / 64.0)
            weights = np.exp(normalise_log_weights(self.log_weights + step * loglik))
            remaining -= step
            idx = RESAMPLERS[cfg.resampler](weights, self.size, rng)
            mean, cov = _weighted_pose(self.particles, weights)
            h = (4.0 / (self.size * 5.0)) ** (1.0 / 7.0)  # Silverman, d = 3
            vals, vecs = np.linalg.eigh(cov)
            noise = (rng.standard_normal((self.size, 3)) * np.sqrt(np.maximum(vals, 0.0))) @ vecs.T
            # Liu & West's shrinkage keeps the set's mean and covariance: the kernel alone
            # would widen the belief by (1 + h^2) at every stage.
            dev = self.particles[idx] - mean
            dev[:, 2] = wrap_angles(dev[:, 2])
            moved = mean + math.sqrt(1.0 - h * h) * dev + h * noise
            moved[:, 2] = wrap_angles(moved[:, 2])
            self.particles = moved
            self.log_weights = np.full(self.size, -math.log(self.size))
            self.last_stages += 1
            loglik = likelihood(moved)
        return remaining * loglik

    def resample(
        self,
        *,
        rng: np.random.Generator,
        injector: Injector | None = None,
        inject_fraction: float = 0.0,
    ) -> None:
        """Draw a KLD-sized particle set by the configured scheme; replace a fraction
        by the injector's draws. Weights become uniform."""
        cfg = self.config
        weights = np.exp(self.log_weights)
        n = self.kld_size(weights, rng=rng)
        n_inject = round(inject_fraction * n) if injector is not None else 0
        if n_inject > 0:
            # Searching again: the full budget, so that injected poses land near the truth.
            n = cfg.max_particles
            n_inject = round(inject_fraction * n)
        idx = RESAMPLERS[cfg.resampler](weights, n - n_inject, rng)
        kept = self.particles[idx]
        if n_inject > 0 and injector is not None:
            fresh = np.asarray(injector(n_inject, rng), dtype=np.float64).reshape(-1, 3)
            fresh[:, 2] = wrap_angles(fresh[:, 2])
            kept = np.vstack([kept, fresh])
        self.particles = kept
        self.log_weights = np.full(len(kept), -math.log(len(kept)))
        self.last_injected = n_inject
        self.unweighed = n_inject

    def kld_size(self, weights: FloatArray, *, rng: np.random.Generator) -> int:
        """Particles needed for the current weighted set (Fox's KLD sampling, vectorised:
        count occupied bins along one random draw of ``max_particles`` samples)."""
        cfg = self.config
        draw = multinomial_resample(weights, cfg.max_particles, rng)
        cells = np.floor(self.particles[draw] / np.asarray(cfg.kld_bin)).astype(np.int64)
        # One integer per (x, y, theta) bin (theta spans < 64 bins; x, y within +-2^20).
        key = (
            ((cells[:, 0] + (1 << 20)) << 27)
            + ((cells[:, 1] + (1 << 20)) << 6)
            + (cells[:, 2] + 32)
        )
        _, first = np.unique(key, return_index=True)
        first.sort()
        # k(n): bins occupied by the first n draws; need the first n with n >= bound(k(n)).
        n_values = np.arange(1, cfg.max_particles + 1)
        k_of_n = np.searchsorted(first, n_values, side="left")
        bound = kld_particle_count(k_of_n, epsilon=cfg.kld_epsilon, z_quantile=cfg.kld_z_quantile)
        ok = np.flatnonzero(n_values >= bound)
        n = int(n_values[ok[0]]) if len(ok) else cfg.max_particles
        return int(min(max(n, cfg.min_particles), cfg.max_particles))

    # ------------------------------------------------------------ estimate
    def estimate(self) -> FilterEstimate:
        """The main mode's weighted mean (circular in theta), its covariance, and whether
        the filter has converged on it.

        The mode: the ``mode_cell_m`` square cell holding the most weight; its core is
        every particle within ``core_radius_m`` and ``core_angle_rad`` of that cell's
        mean. Converged: the core holds ``converged_weight`` of the weight and is
        tighter than ``converged_sigma_m`` / ``converged_sigma_rad`` (a few stray
        particles far away do not hide a converged filter, as they would inflate a
        whole-set covariance).

        Particles injected at the last resampling and not weighed by an observation since
        (`unweighed`) are left out: they are the search's proposals, not the belief. With
        their uniform share of the weight counted, a filter that still injects (its
        long-run likelihood average remembers a scene with more landmarks, as after a
        kidnap) held its main mode at 0.15-0.23 m from the truth for 24 frames without
        ever reaching ``converged_weight`` (MRCLAM-6 robot 5 given robot 2's frames:
        0.35-0.83 of the weight in the core while 500-2 500 of 5 000 particles were
        injected a frame).
        """
        cfg = self.config
        w = np.exp(self.log_weights)
        if 0 < self.unweighed < self.size:
            w[self.size - self.unweighed :] = 0.0
            w /= float(w.sum())
        cells = np.floor(self.particles[:, :2] / cfg.mode_cell_m).astype(np.int64)
        key = (cells[:, 0] + (1 << 24)) * (1 << 26) + (cells[:, 1] + (1 << 24))
        _, inverse = np.unique(key, return_inverse=True)
        best = int(np.argmax(np.bincount(inverse, weights=w)))
        seed_mean, _ = _weighted_pose(self.particles, w * (inverse == best))
        dist = np.hypot(*(self.particles[:, :2] - seed_mean[:2]).T)
        dyaw = np.abs(wrap_angles(self.particles[:, 2] - seed_mean[2]))
        core = (dist <= cfg.core_radius_m) & (dyaw <= cfg.core_angle_rad)
        mean, cov = _weighted_pose(self.particles, w * core)
        core_weight = float(np.sum(w[core]))
        sigma_xy = math.sqrt(max(float(np.linalg.eigvalsh(cov[:2, :2])[-1]), 0.0))
        converged = (
            core_weight >= cfg.converged_weight
            and sigma_xy <= cfg.converged_sigma_m
            and math.sqrt(max(float(cov[2, 2]), 0.0)) <= cfg.converged_sigma_rad
        )
        return FilterEstimate(mean, cov, converged, self.size, self.last_injected, core_weight)


def _weighted_pose(particles: FloatArray, weights: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Weighted mean (circular in theta) ``(3,)`` and covariance ``(3, 3)``."""
    total = float(np.sum(weights))
    w = weights / total if total > 0 else np.full(len(weights), 1.0 / len(weights))
    xy = w @ particles[:, :2]
    theta = math.atan2(float(w @ np.sin(particles[:, 2])), float(w @ np.cos(particles[:, 2])))
    dev = np.column_stack([particles[:, :2] - xy, wrap_angles(particles[:, 2] - theta)])
    cov = (dev * w[:, None]).T @ dev
    return np.array([xy[0], xy[1], theta]), cov


def uniform_injector(
    bounds_xy: tuple[float, float, float, float],
) -> Injector:
    """Uniform poses over ``(xmin, ymin, xmax, ymax)``, any heading."""
    lo = np.array([bounds_xy[0], bounds_xy[1], -math.pi])
    hi = np.array([bounds_xy[2], bounds_xy[3], math.pi])

    def draw(n: int, rng: np.random.Generator) -> FloatArray:
        return lo + rng.random((n, 3)) * (hi - lo)

    return draw
