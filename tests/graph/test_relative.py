"""Relative marginals: the same Gaussian at the linearisation point, correct
Jacobians elsewhere, and indifferent to a rigid motion of the whole map."""

from __future__ import annotations

import math
import pickle

import gtsam
import numpy as np
import pytest

from graph.config import SlamConfig
from graph.factors import bearing_factor, landmark_key, odometry_factor, pose_key
from graph.relative import (
    RelativeMarginalFactor,
    RelativeSpec,
    _Blanket,
    _square_root,
    choose_reference,
    relative_marginal,
)
from graph.types import Odometry

KEYS = [pose_key(0, 5), landmark_key(1), pose_key(0, 9), landmark_key(2)]


def _theta() -> gtsam.Values:
    theta = gtsam.Values()
    theta.insert(KEYS[0], gtsam.Pose2(1.0, 2.0, 0.5))
    theta.insert(KEYS[1], np.array([3.0, 1.0]))
    theta.insert(KEYS[2], gtsam.Pose2(-1.0, 0.5, 2.0))
    theta.insert(KEYS[3], np.array([-2.0, 4.0]))
    return theta


def _random_gaussian(seed: int) -> gtsam.JacobianFactor:
    rng = np.random.default_rng(seed)
    rows = 12
    g = gtsam.GaussianFactorGraph()
    g.add(
        gtsam.JacobianFactor(
            KEYS[0],
            rng.normal(size=(rows, 3)),
            KEYS[1],
            rng.normal(size=(rows, 2)),
            KEYS[2],
            rng.normal(size=(rows, 3)),
            rng.normal(size=rows),
            gtsam.noiseModel.Unit.Create(rows),
        )
    )
    g.add(
        gtsam.JacobianFactor(
            KEYS[3], rng.normal(size=(2, 2)), rng.normal(size=2), gtsam.noiseModel.Unit.Create(2)
        )
    )
    return gtsam.JacobianFactor(g)


def _augmented_hessian(factor: gtsam.GaussianFactor, order: list[int]) -> np.ndarray:
    g = gtsam.GaussianFactorGraph()
    g.add(factor)
    return np.asarray(g.augmentedHessian(gtsam.Ordering(order)))


def _retract(values: gtsam.Values, key: int, step: np.ndarray) -> None:
    if len(step) == 3:
        values.update(key, values.atPose2(key).retract(step))
    else:
        values.update(key, values.atPoint2(key) + step)


@pytest.mark.parametrize("seed", range(3))
def test_same_gaussian_at_the_linearisation_point(seed: int) -> None:
    gaussian = _random_gaussian(seed)
    theta = _theta()
    relative = relative_marginal(gaussian, theta, KEYS[0])
    order = list(gaussian.keys())
    expected = _augmented_hessian(gaussian, order)
    got = _augmented_hessian(relative.linearize(theta), order)
    np.testing.assert_allclose(got, expected, atol=1e-9 * np.abs(expected).max())


def test_jacobians_match_finite_differences_away_from_theta() -> None:
    theta = _theta()
    relative = relative_marginal(_random_gaussian(7), theta, KEYS[0])
    at = gtsam.Values(theta)
    _retract(at, KEYS[2], np.array([0.1, -0.2, 0.3]))
    _retract(at, KEYS[1], np.array([0.3, 0.1]))
    _retract(at, KEYS[0], np.array([-0.05, 0.1, -0.2]))
    linear = relative.linearize(at)
    a, _ = linear.jacobian()
    column = 0
    eps = 1e-6
    for key in linear.keys():
        dim = 2 if gtsam.Symbol(key).chr() == ord("l") else 3
        for c in range(dim):
            step = np.zeros(dim)
            step[c] = eps
            plus, minus = gtsam.Values(at), gtsam.Values(at)
            _retract(plus, key, step)
            _retract(minus, key, -step)
            numeric = (relative.whitenedError(plus) - relative.whitenedError(minus)) / (2 * eps)
            np.testing.assert_allclose(a[:, column], numeric, atol=1e-6)
            column += 1


def _gauge_free_marginal() -> tuple[gtsam.GaussianFactor, gtsam.Values]:
    """Odometry x0-x1-x2 and bearings to two landmarks, no prior; x0 eliminated."""
    cfg = SlamConfig(huber_k=None)
    x = [pose_key(0, k) for k in range(3)]
    lm = [landmark_key(0), landmark_key(1)]
    theta = gtsam.Values()
    poses = [gtsam.Pose2(0, 0, 0), gtsam.Pose2(1.0, 0.1, 0.2), gtsam.Pose2(2.0, 0.3, 0.3)]
    points = [np.array([1.5, 2.0]), np.array([2.5, -1.5])]
    for k, p in zip(x, poses, strict=True):
        theta.insert(k, p)
    for k, p in zip(lm, points, strict=True):
        theta.insert(k, p)
    graph = gtsam.NonlinearFactorGraph()
    for a, b in zip(range(2), range(1, 3), strict=True):
        rel = poses[a].between(poses[b])
        graph.add(odometry_factor(x[a], x[b], Odometry(rel.x(), rel.y(), rel.theta()), cfg))
    for k, p in zip(x, poses, strict=True):
        for key, q in zip(lm, points, strict=True):
            bearing = p.bearing(q).theta()
            graph.add(bearing_factor(k, key, bearing + 0.01, math.radians(1.0), None))
    _, remaining = graph.linearize(theta).eliminatePartialSequential(gtsam.Ordering([x[0]]))
    return gtsam.JacobianFactor(remaining), theta


def test_a_rigid_motion_of_the_map_leaves_a_gauge_free_marginal_unchanged() -> None:
    factor, theta = _gauge_free_marginal()
    reference = choose_reference(list(factor.keys()), [pose_key(0, 0)])
    assert reference == pose_key(0, 1)
    relative = relative_marginal(factor, theta, reference)
    linear = gtsam.LinearContainerFactor(factor, _subset(theta, list(factor.keys())))
    moved = gtsam.Values()
    g = gtsam.Pose2(3.0, -2.0, 0.8)  # the whole map rotated by 0.8 rad and shifted
    for key in factor.keys():
        if gtsam.Symbol(key).chr() == ord("l"):
            moved.insert(key, g.transformFrom(theta.atPoint2(key)))
        else:
            moved.insert(key, g.compose(theta.atPose2(key)))
    assert relative.error(moved) == pytest.approx(relative.error(theta), rel=1e-6)
    # The absolute-coordinate linear marginal mistakes the same motion for a change.
    assert linear.error(moved) > linear.error(theta) + 1.0


def _subset(values: gtsam.Values, keys: list[int]) -> gtsam.Values:
    out = gtsam.Values()
    for key in keys:
        if gtsam.Symbol(key).chr() == ord("l"):
            out.insert(key, values.atPoint2(key))
        else:
            out.insert(key, values.atPose2(key))
    return out


def test_the_spec_pickles_and_rebuilds_the_same_factor() -> None:
    theta = _theta()
    factor = relative_marginal(_random_gaussian(2), theta, KEYS[2])
    again = RelativeMarginalFactor(pickle.loads(pickle.dumps(factor.spec)))
    at = gtsam.Values(theta)
    _retract(at, KEYS[0], np.array([0.2, -0.1, 0.3]))
    assert list(again.keys()) == list(factor.keys())
    assert again.error(at) == pytest.approx(factor.error(at), rel=1e-12)


@pytest.mark.parametrize("seed", range(20))
def test_plain_arithmetic_coordinates_match_gtsam(seed: int) -> None:
    """The error path's plain-float y(x) equals the gtsam-based one, including headings
    across +-pi and relative rotations of (nearly) zero."""
    from graph.relative import _Blanket

    rng = np.random.default_rng(seed)
    theta = _theta()
    blanket = _Blanket(KEYS[0], KEYS, theta)
    moved = gtsam.Values()
    for key in KEYS:
        if key in (KEYS[1], KEYS[3]):
            moved.insert(key, theta.atPoint2(key) + rng.normal(scale=2.0, size=2))
            continue
        pose = theta.atPose2(key)
        if seed % 4 == 0:
            step = np.zeros(3)  # at theta: every relative rotation is exactly zero
        elif seed % 4 == 1:
            step = np.array([rng.normal(), rng.normal(), math.pi - pose.theta() - 1e-9])
        else:
            step = rng.normal(scale=[1.0, 1.0, 3.0])
        moved.insert(key, pose.retract(step))
    expected, _, _ = blanket.evaluate(moved, with_jacobians=False)
    np.testing.assert_allclose(
        blanket.coordinates(blanket.read(moved)), expected, rtol=1e-9, atol=1e-12
    )


def _odometry_marginal(prior: bool) -> tuple[gtsam.GaussianFactor, gtsam.Values]:
    """Odometry x0-x1-x2 whose measurements disagree with theta (so b != 0); x1
    eliminated. With `prior`, x0 also has a prior (absolute information)."""
    cfg = SlamConfig(huber_k=None)
    x = [pose_key(0, k) for k in range(3)]
    poses = [gtsam.Pose2(0.5, -1.0, 0.3), gtsam.Pose2(1.4, -0.6, 0.5), gtsam.Pose2(2.1, 0.2, 0.9)]
    theta = gtsam.Values()
    for k, p in zip(x, poses, strict=True):
        theta.insert(k, p)
    graph = gtsam.NonlinearFactorGraph()
    for a, b, wrong in ((0, 1, (0.05, -0.02, 0.03)), (1, 2, (-0.03, 0.04, -0.02))):
        rel = poses[a].between(poses[b])
        odo = Odometry(rel.x() + wrong[0], rel.y() + wrong[1], rel.theta() + wrong[2])
        graph.add(odometry_factor(x[a], x[b], odo, cfg))
    if prior:
        graph.add(gtsam.PriorFactorPose2(x[0], poses[0], gtsam.noiseModel.Isotropic.Sigma(3, 0.1)))
    _, remaining = graph.linearize(theta).eliminatePartialSequential(gtsam.Ordering([x[1]]))
    return gtsam.JacobianFactor(remaining), theta


def test_a_pose_only_gauge_free_marginal_becomes_a_between_factor() -> None:
    """Two poses, information on their relative pose only: a C++ BetweenFactorPose2 with
    the same Gaussian at the linearisation point (Hessian and gradient), unchanged by a
    rigid motion of the map, and within second order of the relative factor nearby."""
    factor, theta = _odometry_marginal(prior=False)
    reference = choose_reference(list(factor.keys()), [pose_key(0, 1)])
    between = relative_marginal(factor, theta, reference)
    assert isinstance(between, gtsam.BetweenFactorPose2)
    order = list(factor.keys())
    expected = _augmented_hessian(factor, order)
    got = _augmented_hessian(between.linearize(theta), order)
    # [[H, -g], [-g^T, c]]: all but the constant c, which no optimiser sees
    scale = np.abs(expected).max()
    np.testing.assert_allclose(got[:-1], expected[:-1], atol=1e-9 * scale)
    np.testing.assert_allclose(got[:, :-1], expected[:, :-1], atol=1e-9 * scale)

    moved = gtsam.Values()
    g = gtsam.Pose2(-3.0, 2.0, -2.5)
    for key in factor.keys():
        moved.insert(key, g.compose(theta.atPose2(key)))
    assert between.error(moved) == pytest.approx(between.error(theta), rel=1e-9)

    # The relative factor of the same Gaussian, for comparison near theta: their errors
    # agree up to a constant (taken out at theta) to within second order of the step.
    blanket = _Blanket(reference, order, theta)
    a, b = gtsam.JacobianFactor(factor).jacobian()
    keyed = np.hstack([a[:, 3 * order.index(k) : 3 * order.index(k) + 3] for k in blanket.keys])
    spec = RelativeSpec(reference, tuple(blanket.keys), _at(theta, blanket.keys),
                        blanket.right_divide(keyed, theta), np.asarray(b))  # fmt: skip
    relative = RelativeMarginalFactor(spec)
    offset = relative.error(theta) - between.error(theta)
    rng = np.random.default_rng(3)
    for step in (1e-2, 1e-3):
        at = gtsam.Values(theta)
        for key in order:
            _retract(at, key, rng.normal(scale=step, size=3))
        change = abs(relative.error(at) - relative.error(theta))
        assert abs(relative.error(at) - between.error(at) - offset) <= 0.05 * change + 1e-12


def test_a_marginal_with_absolute_information_or_a_landmark_stays_relative() -> None:
    factor, theta = _odometry_marginal(prior=True)
    reference = choose_reference(list(factor.keys()), [pose_key(0, 1)])
    assert isinstance(relative_marginal(factor, theta, reference), RelativeMarginalFactor)
    landmark, theta = _gauge_free_marginal()
    reference = choose_reference(list(landmark.keys()), [pose_key(0, 0)])
    assert isinstance(relative_marginal(landmark, theta, reference), RelativeMarginalFactor)


def _at(values: gtsam.Values, keys: list[int]) -> tuple[tuple[float, ...], ...]:
    out = []
    for key in keys:
        p = values.atPose2(key)
        out.append((p.x(), p.y(), p.theta()))
    return tuple(out)


def test_python_factors_see_isam2s_own_linearisation_point_not_a_copy() -> None:
    """pybind11 hands a Python factor's callback the C++ Values it is evaluated at by
    reusing that object's registered wrapper, and by copying every variable otherwise.
    IncrementalGraph holds iSAM2's linearisation point, so linearising a Python factor
    passes that very object (what made MRCLAM-6 frames ~25 % cheaper)."""
    from graph.isam import IncrementalGraph

    graph = IncrementalGraph(SlamConfig())
    seen: list[bool] = []

    def error(_f: gtsam.CustomFactor, values: gtsam.Values, jac: list | None) -> np.ndarray:
        seen.append(values is graph.linearization_point())
        if jac is not None:
            jac[0] = np.eye(3)
        return gtsam.Pose2.Logmap(values.atPose2(KEYS[0]))

    values = gtsam.Values()
    values.insert(KEYS[0], gtsam.Pose2(0.1, -0.2, 0.3))
    prior = gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(3), gtsam.KeyVector([KEYS[0]]), error)
    graph.update([prior], values)
    assert seen and all(seen)
    assert graph.linearization_point().atPose2(KEYS[0]).equals(gtsam.Pose2(0.1, -0.2, 0.3), 1e-12)


@pytest.mark.parametrize("signs", [(-1.0, 1.0, -1.0), (1.0, -1.0, 1.0), (1.0, 1.0, 1.0)])
def test_a_diagonal_information_root_with_any_signs_becomes_a_between_factor(
    signs: tuple[float, float, float],
) -> None:
    """A gauge-free pose-pair marginal whose square root QR leaves diagonal with
    negative entries (MRCLAM-6 replayed from later start frames raised "sigma values
    must be non-negative" here) is a between factor with the same information."""
    from graph.relative import as_between

    x0, x1 = pose_key(0, 0), pose_key(0, 1)
    root = np.diag(np.array(signs) * np.array([2.0, 3.0, 4.0]))
    spec = RelativeSpec(
        x0, (x0, x1), ((0.0, 0.0, 0.0), (1.0, 0.5, 0.2)), np.hstack([np.zeros((3, 3)), root]),
        np.zeros(3),
    )  # fmt: skip
    between = as_between(spec)
    assert isinstance(between, gtsam.BetweenFactorPose2)
    info = np.asarray(between.noiseModel().R()).T @ np.asarray(between.noiseModel().R())
    np.testing.assert_allclose(info, root.T @ root, atol=1e-12)


@pytest.mark.parametrize("rank", [6, 3], ids=["full rank", "rank-deficient"])
def test_square_root_of_a_hessian_factor_gives_back_its_information(rank: int) -> None:
    """Cholesky where the information has full rank, the eigen-decomposition where it
    has not (a landmark seen along one ray): either way [A | b]^T [A | b] is the
    factor's augmented information."""
    rng = np.random.default_rng(rank)
    rows = rng.normal(size=(rank, 6))
    rhs = rng.normal(size=rank)
    info = rows.T @ rows
    factor = gtsam.HessianFactor(
        KEYS[0],
        KEYS[2],
        info[:3, :3],
        info[:3, 3:],
        rows[:, :3].T @ rhs,
        info[3:, 3:],
        rows[:, 3:].T @ rhs,
        float(rhs @ rhs),
    )
    a, b = _square_root(factor)
    root = np.column_stack([a, b])
    np.testing.assert_allclose(root.T @ root, np.asarray(factor.augmentedInformation()), atol=1e-9)
