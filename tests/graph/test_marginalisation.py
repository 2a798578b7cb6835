"""Marginalising a landmark keeps its information: the remaining estimate and
covariances equal a batch solve in which the landmark was eliminated."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from graph.config import SlamConfig
from graph.factors import (
    bearing_factor,
    landmark_key,
    odometry_factor,
    pose_key,
    pose_prior_factor,
)
from graph.isam import IncrementalGraph
from graph.types import Odometry, Pose2D

SIGMA = 0.02


def _small_problem(
    seed: int,
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, list[int], list[int]]:
    """6 poses on a line, 5 landmarks each seen from every pose; plain Gaussian noise."""
    rng = np.random.default_rng(seed)
    cfg = SlamConfig(huber_k=None)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    poses = [pose_key(0, k) for k in range(6)]
    marks = [landmark_key(j) for j in range(5)]
    truth = [(0.8 * k, 0.1 * math.sin(k), 0.05 * k) for k in range(6)]
    points = rng.uniform([-1.0, 2.0], [5.0, 5.0], size=(5, 2))
    points[::2, 1] *= -1
    graph.add(pose_prior_factor(poses[0], Pose2D(*truth[0]), cfg))
    for k in range(1, 6):
        rel = gtsam.Pose2(*truth[k - 1]).between(gtsam.Pose2(*truth[k]))
        odo = Odometry(
            rel.x() + rng.normal(0, 0.02),
            rel.y() + rng.normal(0, 0.02),
            rel.theta() + rng.normal(0, 0.01),
        )
        graph.add(odometry_factor(poses[k - 1], poses[k], odo, cfg))
    for j, key in enumerate(marks):
        for k, pk in enumerate(poses):
            x, y, th = truth[k]
            b = math.atan2(points[j, 1] - y, points[j, 0] - x) - th + rng.normal(0, SIGMA)
            graph.add(bearing_factor(pk, key, math.remainder(b, 2 * math.pi), SIGMA, None))
    for k, pk in enumerate(poses):
        values.insert(pk, gtsam.Pose2(*truth[k]))
    for j, key in enumerate(marks):
        values.insert(key, points[j] + rng.normal(0, 0.1, 2))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-14)
    params.setMaxIterations(200)
    optimum = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return graph, optimum, poses, marks


def _eliminated_covariance(
    graph: gtsam.NonlinearFactorGraph, at: gtsam.Values, eliminate: int, keys: list[int]
) -> np.ndarray:
    """Batch: linearise the whole graph, eliminate one landmark, invert what remains."""
    linear = graph.linearize(at)
    _, remaining = linear.eliminatePartialSequential(gtsam.Ordering([eliminate]))
    information, _ = remaining.hessian(gtsam.Ordering(keys))
    return np.linalg.inv(information)


@pytest.mark.parametrize("seed", range(5))
def test_marginalising_a_landmark_equals_batch_elimination(seed: int) -> None:
    graph, optimum, poses, marks = _small_problem(seed)
    inc = IncrementalGraph(SlamConfig(huber_k=None))
    inc.update([graph.at(i) for i in range(graph.size())], optimum)
    gone = marks[2]
    inc.update(marginalise=[gone])

    assert gone not in inc
    assert not inc.estimate().exists(gone)
    rest = poses + [m for m in marks if m != gone]
    # Estimate: marginalisation does not move the MAP of the remaining variables (to
    # iSAM2's Gauss-Newton, which leaves deltas under its wildfire threshold behind).
    for key in poses:
        np.testing.assert_allclose(
            inc.estimate().atPose2(key).matrix(), optimum.atPose2(key).matrix(), atol=1e-5
        )
    # Covariances: equal to the batch graph with the landmark eliminated.
    batch = _eliminated_covariance(graph, optimum, gone, rest)
    dims = [3] * len(poses) + [2] * (len(marks) - 1)
    offsets = np.concatenate([[0], np.cumsum(dims)])
    for i, key in enumerate(rest):
        block = batch[offsets[i] : offsets[i + 1], offsets[i] : offsets[i + 1]]
        got = inc.pose_covariance(key) if key in poses else inc.landmark_covariances([key])[0]
        np.testing.assert_allclose(got, block, rtol=1e-6, atol=1e-12)
    # ... and not what deleting the landmark's factors would give (the EKF-style loss).
    deleted = gtsam.NonlinearFactorGraph()
    for i in range(graph.size()):
        if gone not in graph.at(i).keys():
            deleted.add(graph.at(i))
    lost = gtsam.Marginals(deleted, optimum)
    growth = [
        np.trace(lost.marginalCovariance(k)) / np.trace(inc.pose_covariance(k)) for k in poses
    ]
    assert max(growth) > 1.01, "deleting the landmark should lose information"


@pytest.mark.parametrize("how", ["two updates", "jointly", "staged", "thinning"])
def test_marginalising_poses_and_landmarks_together_matches_batch(how: str) -> None:
    """In two updates, in one joint elimination, or staged in one update (the landmark,
    then the poses: as a removal that thins keyframes does; the poses' stage is
    eliminated by Cholesky), or the landmark first and then a thinning alone."""
    graph, optimum, poses, marks = _small_problem(11)
    inc = IncrementalGraph(SlamConfig(huber_k=None))
    inc.update([graph.at(i) for i in range(graph.size())], optimum)
    if how == "jointly":
        inc.update(marginalise=[marks[0], poses[0], poses[1]])
    elif how == "staged":
        inc.marginal_keys = []
        inc.update(marginalise=[marks[0]], then_marginalise=[poses[0], poses[1]])
        # The poses' marginal replaces the landmark's, which never reaches iSAM2.
        assert all(poses[0] not in keys and poses[1] not in keys for keys in inc.marginal_keys)
    elif how == "thinning":
        inc.update(marginalise=[marks[0]])
        inc.update(then_marginalise=[poses[0], poses[1]])
    else:
        inc.update(marginalise=[poses[0], poses[1]])
        inc.update(marginalise=[marks[0]])
    rest_marks = marks[1:]
    full = gtsam.Marginals(graph, optimum)
    for key in rest_marks:
        np.testing.assert_allclose(
            inc.landmark_covariances([key])[0], full.marginalCovariance(key), rtol=1e-6
        )
    np.testing.assert_allclose(
        inc.pose_covariance(poses[-1]), full.marginalCovariance(poses[-1]), rtol=1e-6
    )
    joint = full.jointMarginalCovariance(gtsam.KeyVector(rest_marks))
    expected = np.block([[joint.at(a, b) for b in rest_marks] for a in rest_marks])
    np.testing.assert_allclose(inc.landmark_joint_covariance(rest_marks), expected, rtol=1e-6)
    assert inc.num_variables == len(poses) - 2 + len(rest_marks)


@pytest.mark.parametrize(
    "which",
    [
        ("m0",),  # one landmark: a factor on every pose
        ("m0", "m1"),  # two landmarks sharing no factor: two marginals
        ("p0", "p5"),  # the chain's two ends: two marginals
        ("p0", "p1", "m2"),  # linked through their bearings: one marginal
    ],
)
def test_marginal_spans_predict_the_marginal_factors(which: tuple[str, ...]) -> None:
    graph, optimum, poses, marks = _small_problem(3)
    inc = IncrementalGraph(SlamConfig(huber_k=None))
    inc.update([graph.at(i) for i in range(graph.size())], optimum)
    named = {f"p{i}": k for i, k in enumerate(poses)} | {f"m{j}": k for j, k in enumerate(marks)}
    keys = [named[w] for w in which]
    predicted = sorted(sorted(span) for span in inc.marginal_spans(keys))
    inc.marginal_keys = []
    inc.update(marginalise=keys)
    added = sorted(sorted(k) for k in inc.marginal_keys)
    assert added, "the marginalisation must add a marginal factor"
    assert predicted == added


def test_unknown_key_cannot_be_marginalised() -> None:
    inc = IncrementalGraph(SlamConfig())
    with pytest.raises(KeyError):
        inc.update(marginalise=[landmark_key(99)])
