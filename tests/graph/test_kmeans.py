"""k-means under L1 (k-medians): recovery, determinism, medians, invariants."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from graph.kmeans import cluster_medians, kmeans_l1, l1_distances


def _blobs(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Three well separated blobs of 20 points each (metres) and their true labels."""
    gen = np.random.default_rng(seed)
    means = np.array([[0.0, 0.0], [20.0, 0.0], [0.0, 20.0]])
    truth = np.repeat(np.arange(3), 20)
    points = means[truth] + gen.uniform(-1.0, 1.0, size=(60, 2))
    return points, truth


def _same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    """True when two labelings group the points identically (up to renaming)."""
    pairs = set(zip(a.tolist(), b.tolist(), strict=True))
    return len(pairs) == len(set(a.tolist())) == len(set(b.tolist()))


def test_l1_distances_are_manhattan() -> None:
    d = l1_distances([[0.0, 0.0], [1.0, -2.0]], [[3.0, 4.0]])
    np.testing.assert_allclose(d, [[7.0], [8.0]])


@pytest.mark.parametrize("seed", range(10))
def test_separated_blobs_are_recovered(seed: int) -> None:
    points, truth = _blobs(seed)
    result = kmeans_l1(points, 3, rng=np.random.default_rng(seed), n_init=3)
    assert result.converged
    assert _same_partition(result.labels, truth)
    for c in range(3):
        members = points[result.labels == c]
        np.testing.assert_allclose(result.centres[c], np.median(members, axis=0))


def test_same_seed_gives_same_result_whatever_the_global_state() -> None:
    points = np.random.default_rng(3).uniform(0.0, 10.0, size=(40, 2))
    np.random.seed(1)  # noqa: NPY002 - the global state must not matter
    a = kmeans_l1(points, 5, rng=np.random.default_rng(42))
    np.random.seed(2)  # noqa: NPY002
    np.random.rand(7)  # noqa: NPY002
    b = kmeans_l1(points, 5, rng=np.random.default_rng(42))
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.centres, b.centres)
    assert a.iterations == b.iterations


def test_rng_is_the_only_source_of_randomness() -> None:
    points = np.random.default_rng(3).uniform(0.0, 10.0, size=(40, 2))
    outcomes = {tuple(kmeans_l1(points, 5, rng=np.random.default_rng(s)).labels) for s in range(20)}
    assert len(outcomes) > 1  # different seeds do explore different seedings


def test_k_at_least_n_gives_each_point_its_own_cluster() -> None:
    points = np.array([[3.0, 1.0], [0.0, 0.0], [5.0, 5.0]])
    for k in (3, 4, 10):
        result = kmeans_l1(points, k, rng=np.random.default_rng(0))
        np.testing.assert_array_equal(result.labels, [0, 1, 2])
        np.testing.assert_array_equal(result.centres, points)
        assert result.cost == 0.0


def test_duplicates_share_a_cluster_when_k_exceeds_distinct_points() -> None:
    points = np.array([[1.0, 1.0], [2.0, 2.0], [1.0, 1.0], [-0.0, 0.0], [0.0, 0.0]])
    result = kmeans_l1(points, 4, rng=np.random.default_rng(0))
    np.testing.assert_array_equal(result.labels, [0, 1, 0, 2, 2])
    assert result.centres.shape == (3, 2)


def test_all_points_identical() -> None:
    points = np.ones((6, 2))
    result = kmeans_l1(points, 2, rng=np.random.default_rng(0))
    np.testing.assert_array_equal(result.labels, np.zeros(6))
    np.testing.assert_array_equal(result.centres, [[1.0, 1.0]])


def test_many_duplicates_with_fewer_clusters_than_distinct_points() -> None:
    points = np.repeat(np.array([[0.0, 0.0], [1.0, 0.0], [5.0, 5.0], [9.0, 0.0]]), 5, axis=0)
    for seed in range(20):
        result = kmeans_l1(points, 3, rng=np.random.default_rng(seed))
        assert result.centres.shape == (3, 2)
        assert np.all(np.bincount(result.labels, minlength=3) > 0)
        assert len(set(result.labels[:5].tolist())) == 1  # duplicates never split


def test_centre_is_coordinate_wise_median_not_mean() -> None:
    # one far outlier: the mean moves, the L1 minimiser (median) does not
    points = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 10.0], [100.0, 1.0]])
    centres = cluster_medians(points, np.zeros(4, dtype=np.int64), 1)
    np.testing.assert_allclose(centres, [[1.5, 0.5]])
    odd = cluster_medians(points[:3], np.zeros(3, dtype=np.int64), 1)
    np.testing.assert_allclose(odd, [[1.0, 0.0]])


def test_median_minimises_the_summed_l1_distance() -> None:
    gen = np.random.default_rng(5)
    points = gen.standard_cauchy(size=(31, 2))
    centre = cluster_medians(points, np.zeros(31, dtype=np.int64), 1)[0]
    best = np.abs(points - centre).sum()
    for trial in centre + gen.normal(scale=0.3, size=(200, 2)):
        assert np.abs(points - trial).sum() >= best - 1e-12


def test_convention_ties_go_to_the_lowest_centre_index() -> None:
    # at convergence the centres sit on (0, 0) and (4, 0); (2, 0) is 2 m from both
    points = np.array([[0.0, 0.0], [0.0, 0.0], [4.0, 0.0], [4.0, 0.0], [2.0, 0.0]])
    for seed in range(20):
        result = kmeans_l1(points, 2, rng=np.random.default_rng(seed))
        d = l1_distances(points, result.centres)
        assert d[4, 0] == d[4, 1] == 2.0
        assert result.labels[4] == 0


@pytest.mark.parametrize("k", [0, -1])
def test_non_positive_k_is_refused(k: int) -> None:
    with pytest.raises(ValueError, match="k must be"):
        kmeans_l1(np.zeros((3, 2)), k, rng=np.random.default_rng(0))


@pytest.mark.parametrize(
    "points",
    [np.zeros((0, 2)), np.zeros((3, 3)), np.zeros(4), np.array([[0.0, np.nan]])],
)
def test_bad_points_are_refused(points: np.ndarray) -> None:
    with pytest.raises(ValueError):
        kmeans_l1(points, 2, rng=np.random.default_rng(0))


def test_more_restarts_never_cost_more() -> None:
    points = np.random.default_rng(9).uniform(0.0, 10.0, size=(50, 2))
    for seed in range(5):
        one = kmeans_l1(points, 6, rng=np.random.default_rng(seed))
        many = kmeans_l1(points, 6, rng=np.random.default_rng(seed), n_init=4)
        assert many.cost <= one.cost  # the first of the 4 runs is the single run


coords = st.integers(-20, 20).map(float) | st.floats(-1e3, 1e3, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(
    points=arrays(np.float64, st.tuples(st.integers(1, 40), st.just(2)), elements=coords),
    k=st.integers(1, 8),
    seed=st.integers(0, 2**32 - 1),
)
def test_invariants_at_convergence(points: np.ndarray, k: int, seed: int) -> None:
    result = kmeans_l1(points, k, rng=np.random.default_rng(seed))
    n_distinct = len(np.unique(points + 0.0, axis=0))
    k_eff = min(k, n_distinct)
    assert result.converged
    assert result.labels.shape == (len(points),)
    assert result.labels.dtype == np.int64
    assert result.centres.shape == (k_eff, 2)
    assert result.labels.min() >= 0
    assert result.labels.max() < k_eff
    assert np.all(np.bincount(result.labels, minlength=k_eff) > 0)  # no empty cluster
    # every point sits with an L1-nearest centre
    d = l1_distances(points, result.centres)
    own = d[np.arange(len(points)), result.labels]
    scale = 1.0 + np.abs(points).max()
    assert np.all(own <= d.min(axis=1) + 1e-12 * scale)
    # every centre is the coordinate-wise median of its members
    np.testing.assert_allclose(
        result.centres, cluster_medians(points, result.labels, k_eff), rtol=0, atol=0
    )
    np.testing.assert_allclose(result.cost, own.sum(), rtol=1e-12, atol=1e-12 * scale)
