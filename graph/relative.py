"""Marginal factors expressed relative to a reference pose.

Marginalising the oldest pose of a window leaves a dense Gaussian on its
Markov blanket (the next pose, the landmarks it saw, ...). Wrapped as a
``LinearContainerFactor`` that Gaussian is linear in *absolute* coordinates:
its Jacobians are frozen at the linearisation point, so when a later loop
closure rotates or shifts the map as a whole, the frozen prior pulls the
landmarks against the poses. Bearing-only maps move a lot after their first
estimate, and this error compounds window after window.

`relative_marginal` re-expresses the same Gaussian in coordinates that a rigid
motion of the map leaves unchanged except for the reference pose itself:

    y_R = Log(R0^-1 R)                         the reference pose (absolute)
    y_P = Log((R0^-1 P0)^-1 (R^-1 P))          other poses, relative to R
    y_L = R^-1 L - R0^-1 L0                    landmarks, in R's frame

At the linearisation point y = 0 and y ~ T delta (delta: the local coordinates
of the blanket), so the Gaussian ``|A delta - b|^2`` becomes
``|A T^-1 y(x) - b|^2``: the same information at the linearisation point, but
a nonlinear factor that is relinearised like any other (nonlinear factor
recovery, cf. Mazuran et al., RSS 2014).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray

from graph.factors import is_landmark_key

FloatArray = NDArray[np.float64]


class _Blanket:
    """The variables of a relative marginal and the map y(x) to relative coordinates."""

    def __init__(self, reference: int, keys: Sequence[int], theta: gtsam.Values) -> None:
        self.reference = reference
        self.poses = [k for k in keys if k != reference and not is_landmark_key(k)]
        self.landmarks = [k for k in keys if is_landmark_key(k)]
        self.pose_keys = [reference, *self.poses]
        self.keys = [*self.pose_keys, *self.landmarks]
        self.dims = [3] + [3] * len(self.poses) + [2] * len(self.landmarks)
        self.offsets = np.concatenate([[0], np.cumsum(self.dims)]).astype(int)
        self.r0 = theta.atPose2(reference)
        self.q0 = [self.r0.between(theta.atPose2(k)) for k in self.poses]
        self.l0 = (
            np.array([self.r0.transformTo(theta.atPoint2(k)) for k in self.landmarks])
            if self.landmarks
            else np.zeros((0, 2))
        )
        # Plain floats for `coordinates`: (x, y, cos, sin) of R0 and of each Q0.
        self._r0 = _plain(self.r0)
        self._q0 = [_plain(q) for q in self.q0]
        self._l0 = [float(c) for c in self.l0.ravel()]

    def read(self, values: gtsam.Values) -> tuple[float, ...]:
        """The blanket's variables in `values` as plain floats: (x, y, theta) of the
        reference and of every other pose, then (x, y) of every landmark."""
        out: list[float] = []
        for k in self.pose_keys:
            p = values.atPose2(k)
            out += (p.x(), p.y(), p.theta())
        for k in self.landmarks:
            out.extend(values.atPoint2(k).tolist())
        return tuple(out)

    def coordinates(self, raw: Sequence[float]) -> FloatArray:
        """y at the variables `raw` (as `read` gives them), the same numbers as
        ``evaluate(values, False)[0]`` but in plain Python arithmetic: an optimiser's
        step test evaluates every factor's error, and for blankets of a few keys numpy's
        per-call overhead dominated (MRCLAM-6 at cap 8: ~160 error calls per frame)."""
        r = _from_xyt(raw[0], raw[1], raw[2])
        out = _log(_between(self._r0, r))
        for j, q in enumerate(self._q0, start=1):
            p = _from_xyt(raw[3 * j], raw[3 * j + 1], raw[3 * j + 2])
            out.extend(_log(_between(q, _between(r, p))))
        rx, ry, rc, rs = r
        base = 3 * len(self.pose_keys)
        for j in range(len(self.landmarks)):
            dx, dy = raw[base + 2 * j] - rx, raw[base + 2 * j + 1] - ry
            out.append(rc * dx + rs * dy - self._l0[2 * j])
            out.append(-rs * dx + rc * dy - self._l0[2 * j + 1])
        return np.array(out)

    def _landmark_rows(self, r: gtsam.Pose2, values: gtsam.Values) -> FloatArray:
        """R^-1 L for every landmark of the blanket, one row each."""
        if not self.landmarks:
            return np.zeros((0, 2))
        points = np.array([values.atPoint2(k) for k in self.landmarks])
        c, s = np.cos(r.theta()), np.sin(r.theta())
        d = points - np.array([r.x(), r.y()])
        return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])

    def evaluate(
        self, values: gtsam.Values, with_jacobians: bool
    ) -> tuple[FloatArray, FloatArray, list[FloatArray]]:
        """y(values) and, if asked, dy/dx in its sparse form: the reference pose's full
        column block (len(y), 3) and, for every other key, its diagonal block (the rows
        of its own y). One pass over the blanket serves both (the error callback wants
        them together)."""
        n = int(self.offsets[-1])
        out = np.empty(n)
        column = np.zeros((n, 3) if with_jacobians else (0, 3))
        diagonal: list[FloatArray] = []
        r = values.atPose2(self.reference)
        e = self.r0.between(r)
        out[0:3] = gtsam.Pose2.Logmap(e)
        if with_jacobians:
            column[0:3] = gtsam.Pose2.LogmapDerivative(e)
        for j, k in enumerate(self.poses):
            o = self.offsets[1 + j]
            p = values.atPose2(k)
            e = self.q0[j].between(r.between(p))
            out[o : o + 3] = gtsam.Pose2.Logmap(e)
            if with_jacobians:
                d = np.asarray(gtsam.Pose2.LogmapDerivative(e))
                diagonal.append(d)
                # R -> R Exp(xi): q0^-1 R^-1 P -> (q0^-1 R^-1 P) Exp(-Ad(P^-1 R) xi)
                column[o : o + 3] = -d @ np.asarray(p.between(r).AdjointMap())
        base = self.offsets[1 + len(self.poses)]
        rows = self._landmark_rows(r, values)
        out[base:] = (rows - self.l0).ravel()
        if with_jacobians and len(rows):
            # R -> R Exp(xi) moves R^-1 L by (-v - omega x R^-1 L) to first order.
            column[base::2] = np.column_stack(
                [-np.ones(len(rows)), np.zeros(len(rows)), rows[:, 1]]
            )
            column[base + 1 :: 2] = np.column_stack(
                [np.zeros(len(rows)), -np.ones(len(rows)), -rows[:, 0]]
            )
            rot_t = np.asarray(r.rotation().matrix()).T
            diagonal.extend(rot_t for _ in self.landmarks)
        return out, column, diagonal

    def right_divide(self, a: FloatArray, values: gtsam.Values) -> FloatArray:
        """A T^-1 for T = dy/dx at `values`, using T's structure: the reference's
        block column plus a block diagonal. With T = [[D0, 0], [C, D]],
        (A T^-1)_i = A_i D_i^-1 for the other keys and
        (A T^-1)_0 = (A_0 - sum_i (A T^-1)_i C_i) D0^-1."""
        _, column, diagonal = self.evaluate(values, with_jacobians=True)
        out = np.empty_like(a)
        o = self.offsets
        acc = a[:, 0:3].copy()
        for i, block in enumerate(diagonal):
            cols = slice(o[1 + i], o[2 + i])
            out[:, cols] = np.linalg.solve(block.T, a[:, cols].T).T
            acc -= out[:, cols] @ column[cols]
        out[:, 0:3] = np.linalg.solve(column[0:3].T, acc.T).T
        return out


_Plain = tuple[float, float, float, float]
"""A pose as (x, y, cos theta, sin theta)."""


def _plain(pose: gtsam.Pose2) -> _Plain:
    return _from_xyt(pose.x(), pose.y(), pose.theta())


def _from_xyt(x: float, y: float, theta: float) -> _Plain:
    return (x, y, math.cos(theta), math.sin(theta))


def _between(a: _Plain, b: _Plain) -> _Plain:
    """A^-1 B."""
    ax, ay, ac, as_ = a
    bx, by, bc, bs = b
    dx, dy = bx - ax, by - ay
    return (ac * dx + as_ * dy, -as_ * dx + ac * dy, ac * bc + as_ * bs, ac * bs - as_ * bc)


def _log(pose: _Plain) -> list[float]:
    """Pose2.Logmap, written as GTSAM's: V(w)^-1 t for the rotation w."""
    x, y, c, s = pose
    w = math.atan2(s, c)
    if abs(w) < 1e-10:
        return [x, y, w]
    c1 = c - 1.0
    det = c1 * c1 + s * s
    ux, uy = c * x + s * y - x, -s * x + c * y - y
    return [-uy * w / det, ux * w / det, w]


_WELL_CONDITIONED = 1e-10
"""Smallest Cholesky pivot, relative to the largest, for which `_square_root` keeps the
Cholesky factor (pivots squared: the scale of H's eigenvalues)."""


def _square_root(factor: gtsam.GaussianFactor) -> tuple[FloatArray, FloatArray]:
    """[A | b] with [A | b]^T [A | b] = the factor's augmented information.

    A Jacobian factor (what QR elimination of Jacobian factors leaves) already is
    one. A Hessian factor [[H, g], [g^T, f]] is factored by Cholesky of H where H is
    well conditioned: A = [R; 0], b = [R^-T g; sqrt(f - |R^-T g|^2)] with R^T R = H.
    Otherwise by eigen-decomposition: a marginal is often rank-deficient (a landmark
    seen along one ray only), which Cholesky and GaussianFactor.jacobian() refuse
    (IndeterminantLinearSystem); the eigen-decomposition is ~10x the cost.
    """
    if isinstance(factor, gtsam.JacobianFactor):
        a, b = factor.jacobian()  # whitened
        return np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    info = np.asarray(factor.augmentedInformation(), dtype=np.float64)
    info = 0.5 * (info + info.T)
    h, g, f = info[:-1, :-1], info[:-1, -1], float(info[-1, -1])
    try:
        r = np.linalg.cholesky(h).T
    except np.linalg.LinAlgError:
        r = None
    if r is not None:
        pivots = np.diag(r) ** 2
        if pivots.min() > _WELL_CONDITIONED * pivots.max():
            d = np.linalg.solve(r.T, g)
            tail = math.sqrt(max(f - float(d @ d), 0.0))
            a = np.vstack([r, np.zeros((1, r.shape[1]))])
            return a, np.append(d, tail)
    w, v = np.linalg.eigh(info)
    keep = w > 1e-12 * max(float(w[-1]), 1e-300)
    root = np.sqrt(w[keep])[:, None] * v[:, keep].T
    return root[:, :-1], root[:, -1]


@dataclass(frozen=True)
class RelativeSpec:
    """Everything a relative marginal is made of, as plain data (it pickles, unlike
    the factor's Python callback): the blanket's keys with their values at the
    linearisation point, and the square-root information in relative coordinates."""

    reference: int
    keys: tuple[int, ...]
    at: tuple[tuple[float, ...], ...]
    """Per key: (x, y, theta) of a pose or (x, y) of a landmark, at linearisation."""
    m: FloatArray
    b: FloatArray

    def theta(self) -> gtsam.Values:
        values = gtsam.Values()
        for key, v in zip(self.keys, self.at, strict=True):
            if is_landmark_key(key):
                values.insert(key, np.asarray(v, dtype=np.float64))
            else:
                values.insert(key, gtsam.Pose2(*v))
        return values


_RECENT_ERRORS = 8
"""Residuals a relative marginal remembers, by the exact values of its variables. An
iSAM2 dogleg step evaluates the whole graph's error at the linearisation point and at
trial points; most of a factor's variables keep their values from frame to frame, so
on MRCLAM-6 (cap 8) about half of the error calls repeat one of the last 8 inputs."""


class RelativeMarginalFactor(gtsam.CustomFactor):
    """The nonlinear factor of a `RelativeSpec` (see the module docstring)."""

    def __init__(self, spec: RelativeSpec) -> None:
        blanket = _Blanket(spec.reference, spec.keys, spec.theta())
        m, b = spec.m, spec.b
        offsets = blanket.offsets

        recent: dict[tuple[float, ...], FloatArray] = {}

        def error(
            _factor: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[FloatArray] | None
        ) -> FloatArray:
            if jacobians is None:
                raw = blanket.read(values)
                cached = recent.get(raw)
                if cached is None:
                    cached = recent[raw] = m @ blanket.coordinates(raw) - b
                    if len(recent) > _RECENT_ERRORS:
                        del recent[next(iter(recent))]  # the oldest
                return cached
            y, column, diagonal = blanket.evaluate(values, with_jacobians=True)
            jacobians[0] = m @ column
            for i, block in enumerate(diagonal):
                o, e = offsets[1 + i], offsets[2 + i]
                jacobians[1 + i] = m[:, o:e] @ block
            return m @ y - b

        super().__init__(
            gtsam.noiseModel.Unit.Create(m.shape[0]), gtsam.KeyVector(blanket.keys), error
        )
        self.spec = spec


def relative_marginal(
    factor: gtsam.GaussianFactor, theta: gtsam.Values, reference: int
) -> gtsam.NoiseModelFactor:
    """The Gaussian `factor` (linearised at `theta`) as a nonlinear factor relative to
    the pose `reference`, which must be one of its keys: a `RelativeMarginalFactor`, or
    the `BetweenFactorPose2` of `as_between` where that one is the same factor."""
    keys = list(factor.keys())
    blanket = _Blanket(reference, keys, theta)
    a, b = _square_root(factor)  # columns in the order of factor.keys()
    # Reorder A's columns to the blanket's key order.
    dims = {k: (2 if is_landmark_key(k) else 3) for k in keys}
    offsets = np.concatenate([[0], np.cumsum([dims[k] for k in keys])]).astype(int)
    starts = dict(zip(keys, offsets[:-1], strict=True))
    a = np.hstack([a[:, starts[k] : starts[k] + dims[k]] for k in blanket.keys])
    m = blanket.right_divide(a, theta)  # A T^-1, where y ~ T delta at theta
    at = tuple(
        tuple(float(c) for c in theta.atPoint2(k))
        if is_landmark_key(k)
        else (theta.atPose2(k).x(), theta.atPose2(k).y(), theta.atPose2(k).theta())
        for k in blanket.keys
    )
    spec = RelativeSpec(reference, tuple(blanket.keys), at, m, b)
    return as_between(spec) or RelativeMarginalFactor(spec)


def as_between(spec: RelativeSpec, *, tol: float = 1e-9) -> gtsam.BetweenFactorPose2 | None:
    """The relative marginal `spec` as a `BetweenFactorPose2`, evaluated in C++, when it
    is one: two poses, and no information on the reference pose's absolute coordinates
    (``m[:, :3] = 0``: what marginalising poses linked only by odometry leaves; about half
    of the relative marginals on MRCLAM-6, whose robots go seconds without a sighting),
    with full-rank information on the other pose. Else None.

    With ``m = [0 | M]`` reduced by QR to ``M = Q S`` (S 3x3) and ``b' = Q^T b``, the
    factor is ``|S y - b'|^2`` in ``y = Log(Q0^-1 R^-1 P)``. The between factor measures
    ``Q* = Q0 Exp(y*)`` with ``S y* = b'`` and has square-root information ``S J^-1``,
    J being the derivative of ``Log(Q*^-1 Q0 Exp(d))`` at d = 0. Since ``J^-1 y* = y*``
    (true of SE(2)'s Log), its linearisation at the linearisation point is ``S d - b'``:
    the same Gaussian, and like the relative factor it depends on ``R^-1 P`` only. The
    two differ only beyond first order away from the linearisation point."""
    if len(spec.keys) != 2 or is_landmark_key(spec.keys[1]):
        return None
    m, b = spec.m, spec.b
    scale = float(np.abs(m).max(initial=0.0))
    if scale == 0.0 or float(np.abs(m[:, :3]).max()) > tol * scale or m.shape[0] < 3:
        return None
    q, s = np.linalg.qr(m[:, 3:6])
    diagonal = np.abs(np.diag(s))
    if diagonal.min() <= tol * diagonal.max():
        return None  # rank-deficient: no information along some direction
    y_star = np.linalg.solve(s, q.T @ b)
    q0 = gtsam.Pose2(*spec.at[0]).between(gtsam.Pose2(*spec.at[1]))
    measured = q0.compose(gtsam.Pose2.Expmap(y_star))
    jacobian = np.asarray(gtsam.Pose2.LogmapDerivative(gtsam.Pose2.Expmap(-y_star)))
    upper = np.linalg.qr(np.linalg.solve(jacobian.T, s.T).T, mode="r")
    # QR leaves the diagonal's signs free; GTSAM reads a diagonal root as 1 / sigmas and
    # refuses negative ones. Flipping rows keeps root^T root, the information.
    root = np.where(np.diag(upper) < 0.0, -1.0, 1.0)[:, None] * upper
    noise = gtsam.noiseModel.Gaussian.SqrtInformation(root)
    return gtsam.BetweenFactorPose2(spec.keys[0], spec.keys[1], measured, noise)


def choose_reference(keys: Sequence[int], marginalised: Sequence[int]) -> int | None:
    """The blanket pose to anchor a relative marginal at: the oldest pose of the
    marginalised pose's own trajectory, else the oldest pose; None if no pose."""
    poses = sorted(k for k in keys if not is_landmark_key(k))
    if not poses:
        return None
    chains = {gtsam.Symbol(k).index() >> 40 for k in marginalised if not is_landmark_key(k)}
    same = [k for k in poses if gtsam.Symbol(k).index() >> 40 in chains]
    return (same or poses)[0]
