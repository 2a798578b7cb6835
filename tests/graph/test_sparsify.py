"""graph.sparsify: Chow-Liu trees of dense marginals, and maps kept sparse by them."""

from __future__ import annotations

import functools
import math

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from graph.config import SlamConfig
from graph.factors import is_landmark_key, pose_key
from graph.slam import BearingSlam
from graph.snapshot import capture, restore
from graph.sparsify import (
    _Marginals,
    chow_liu_tree,
    kl_divergence,
    marginal_information,
    tree_factors,
)
from tests.graph._world import circle_frames
from tests.graph.test_gauge import _rotation_cost


def _offsets(dims: list[int]) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(dims)]).astype(int)


def _tree_gaussian(
    dims: list[int],
    edges: list[tuple[int, int]],
    rng: np.random.Generator,
    *,
    relative: bool,
    rows: int | None = None,
) -> np.ndarray:
    """Augmented information of a sum of random binary factors over `edges` (a tree).
    `relative`: each factor sees only x_c - x_p on the shared dimensions (no absolute
    part: a rigid shift of every variable is free, as in a gauge-free marginal)."""
    o = _offsets(dims)
    n = int(o[-1])
    blocks = []
    for c, p in edges:
        m = rows if rows is not None else dims[c] + 1
        a = np.zeros((m, n + 1))
        if relative:
            k = min(dims[c], dims[p])
            j = rng.normal(size=(m, k))
            a[:, o[c] : o[c] + k] = j
            a[:, o[p] : o[p] + k] = -j
        else:
            a[:, o[c] : o[c + 1]] = rng.normal(size=(m, dims[c]))
            a[:, o[p] : o[p + 1]] = rng.normal(size=(m, dims[p]))
        a[:, -1] = rng.normal(size=m)
        blocks.append(a)
    stacked = np.vstack(blocks)
    return stacked.T @ stacked


def _random_tree(n: int, rng: np.random.Generator) -> list[tuple[int, int]]:
    return [(c, int(rng.integers(0, c))) for c in range(1, n)]


@settings(max_examples=25, deadline=None, derandomize=True)
@given(
    seed=st.integers(0, 10_000),
    n=st.integers(2, 7),
    relative=st.booleans(),
)
def test_a_marginal_that_is_a_tree_is_its_own_chow_liu_tree(
    seed: int, n: int, relative: bool
) -> None:
    """Tree-structured marginals (absolute, or relative and so gauge-free and rank
    deficient) come back exactly: same edges, same augmented information, KL 0."""
    rng = np.random.default_rng(seed)
    dims = [int(d) for d in rng.choice([2, 3], size=n)]
    dims[0] = 3
    edges = _random_tree(n, rng)
    exact = _tree_gaussian(dims, edges, rng, relative=relative)
    tree = chow_liu_tree(exact, dims)
    assert {frozenset(e) for e in tree.edges} == {frozenset(e) for e in edges}
    scale = np.abs(exact).max()
    np.testing.assert_allclose(tree.information, exact, atol=1e-8 * scale)
    assert kl_divergence(exact[:-1, :-1], tree.information[:-1, :-1]) == pytest.approx(
        0.0, abs=1e-8
    )


def test_a_gauge_free_marginal_gives_a_gauge_free_tree_without_a_root_factor() -> None:
    """No absolute information is invented: shifting every variable costs the tree
    nothing, and the root has no unary factor."""
    rng = np.random.default_rng(3)
    dims = [3, 3, 3, 3, 3]
    # A dense, relative Gaussian: a loop of relative factors (not a tree).
    exact = _tree_gaussian(
        dims, [(1, 0), (2, 1), (3, 2), (4, 3), (0, 4), (2, 0)], rng, relative=True
    )
    tree = chow_liu_tree(exact, dims)
    shift = np.tile([0.3, -0.2, 0.1], len(dims))
    info = tree.information[:-1, :-1]
    assert shift @ info @ shift == pytest.approx(0.0, abs=1e-9 * np.abs(info).max())
    assert all(len(f.vars) == 2 for f in tree.factors)


@settings(max_examples=25, deadline=None, derandomize=True)
@given(seed=st.integers(0, 10_000), n=st.integers(3, 7), relative=st.booleans())
def test_kl_of_a_tree_of_a_dense_marginal_is_positive_and_the_edges_keep_their_marginals(
    seed: int, n: int, relative: bool
) -> None:
    """A dense marginal loses something (KL > 0, finite where pairs are informative),
    and the tree keeps each edge's pairwise marginal exactly (Chow-Liu's moment match)."""
    rng = np.random.default_rng(seed)
    dims = [3] * n
    edges = [(i, j) for i in range(n) for j in range(i)]
    exact = _tree_gaussian(dims, edges, rng, relative=relative, rows=4)
    tree = chow_liu_tree(exact, dims)
    kl = kl_divergence(exact[:-1, :-1], tree.information[:-1, :-1])
    assert kl > 1e-6 and math.isfinite(kl)
    assert tree.kl == pytest.approx(kl, rel=1e-6)
    o = _offsets(dims)
    for c, p in tree.edges:
        cols = [*range(o[c], o[c + 1]), *range(o[p], o[p + 1])]
        np.testing.assert_allclose(
            marginal_information(tree.information, cols),
            marginal_information(exact, cols),
            atol=1e-7 * np.abs(exact).max(),
        )


@settings(max_examples=40, deadline=None, derandomize=True)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 9), relative=st.booleans())
def test_marginals_from_one_decomposition_equal_each_schur_complement(
    seed: int, n: int, relative: bool
) -> None:
    """Every variable's and every pair's augmented marginal taken from one
    eigen-decomposition of the whole information equals the generalised Schur complement
    of the rest, for dense marginals with an absolute part and for gauge-free ones."""
    rng = np.random.default_rng(seed)
    dims = [int(d) for d in rng.choice([2, 3], size=n)]
    dims[0] = 3
    edges = [(i, j) for i in range(n) for j in range(i) if rng.random() < 0.6]
    edges += [(c, p) for c, p in _random_tree(n, rng) if (c, p) not in edges]
    exact = _tree_gaussian(dims, edges, rng, relative=relative)
    marginals = _Marginals(exact)
    o = _offsets(dims)
    scale = np.abs(exact).max()
    for variables in [(i,) for i in range(n)] + [(i, j) for i in range(n) for j in range(i)]:
        cols = [c for v in variables for c in range(o[v], o[v + 1])]
        np.testing.assert_allclose(
            marginals.of(cols), marginal_information(exact, cols), atol=1e-7 * scale
        )


def test_kl_is_zero_for_itself_and_infinite_for_a_lost_direction() -> None:
    rng = np.random.default_rng(1)
    a = rng.normal(size=(8, 6))
    h = a.T @ a
    assert kl_divergence(h, h) == pytest.approx(0.0, abs=1e-10)
    assert kl_divergence(h, 2.0 * h) > 0.0
    assert kl_divergence(h, np.zeros_like(h)) == math.inf


def test_tree_factors_keep_the_keys_and_sum_to_the_tree() -> None:
    """The gtsam factors of a tree: binary (or the root's unary) over the factor's keys,
    and their summed information is the tree's."""
    rng = np.random.default_rng(2)
    keys = [pose_key(0, 1), pose_key(0, 2), gtsam.symbol("L", 4), pose_key(0, 3)]
    dims = [2 if is_landmark_key(k) else 3 for k in keys]
    m = sum(dims) + 2
    a = [rng.normal(size=(m, d)) for d in dims]
    unit = gtsam.noiseModel.Unit.Create(m)
    graph = gtsam.GaussianFactorGraph()
    b = rng.normal(size=m)
    graph.add(gtsam.JacobianFactor(keys[0], a[0], keys[1], a[1], keys[2], a[2], b, unit))
    graph.add(gtsam.JacobianFactor(keys[2], a[2], keys[3], a[3], rng.normal(size=m), unit))
    dense = gtsam.JacobianFactor(graph, gtsam.Ordering(keys))
    factors, tree = tree_factors(dense)
    assert all(len(f.keys()) in (1, 2) and set(f.keys()) <= set(keys) for f in factors)
    summed = gtsam.GaussianFactorGraph()
    for f in factors:
        summed.add(f)
    info = np.asarray(summed.augmentedHessian(gtsam.Ordering(keys)))
    np.testing.assert_allclose(info, tree.information, atol=1e-8 * np.abs(info).max())


@functools.cache
def _bounded_run(sparsification: str, bound: int = 6, frames: int = 260) -> BearingSlam:
    """A capped run (window 10, at most 40 keyframes: the first pose is marginalised);
    asserts after every frame that no factor links more than `bound` keyframes."""
    run, _, _ = circle_frames(frames, seed=5, n_landmarks=30)
    cfg = SlamConfig(
        landmark_cap=8,
        window_observations=None,
        pose_window=10,
        max_keyframes=40,
        keyframe_distance_m=0.2,
        max_linked_keyframes=bound,
        marginal_sparsification=sparsification,  # type: ignore[arg-type]
    )
    slam = BearingSlam(cfg, rng=np.random.default_rng(0))
    slam.graph.sparsification_kl = []
    for f in run:
        slam.process(f, with_covariance=False)
        slam.upkeep()  # the sparsifications a frame leaves (as the service runs it)
        keyframes = {k for k, _ in slam._robots["r1"].keyframes}
        graph = slam.graph.nonlinear_graph()
        linked = [len(keyframes.intersection(graph.at(i).keys())) for i in range(graph.size())]
        assert max(linked, default=0) <= bound
    return slam


def test_a_bounded_run_with_chow_liu_keeps_every_keyframe_and_no_dense_factor() -> None:
    """With sparsification, no factor links more than the bound of keyframes after any
    frame, no keyframe is thinned (they are bounded by max_keyframes and spacing alone:
    more of them than thinning keeps), and the trajectory stays good."""
    frames, truth, _ = circle_frames(260, seed=5, n_landmarks=30)
    sparse = _bounded_run("chow_liu")
    thinned = _bounded_run("thin_keyframes")
    assert sparse.graph.sparsifications > 0, "the run must exercise sparsification"
    kl = sparse.graph.sparsification_kl
    assert kl is not None and len(kl) == sparse.graph.sparsifications
    assert all(k >= 0.0 for k in kl)
    assert len(sparse._robots["r1"].keyframes) > len(thinned._robots["r1"].keyframes)
    traj = sparse.trajectory()["r1"]
    assert len(traj) == len(frames) and np.all(np.isfinite(traj[:, 2:]))
    err = np.hypot(traj[:, 2] - truth[:, 0], traj[:, 3] - truth[:, 1])
    assert float(np.sqrt(np.mean(err**2))) < 1.0


def test_a_sparsified_map_keeps_its_frame() -> None:
    """Rotating the whole sparsified map by 2 degrees costs at least half of what the
    initial-pose prior alone charges, (2 / 0.5)^2 / 2 = 8, as it does the map that thins
    keyframes instead: the trees keep the marginals' absolute part. (They need not charge
    the same: a Chow-Liu tree keeps its edges' pairwise marginals, not every direction's
    information; 142 against 63 on this run.)"""
    angle = math.radians(2.0)
    sparse = _bounded_run("chow_liu")
    thinned = _bounded_run("thin_keyframes")
    assert pose_key(0, 0) not in sparse.graph
    assert _rotation_cost(sparse, angle) > 4.0
    assert _rotation_cost(thinned, angle) > 4.0


def test_a_sparsified_map_survives_a_snapshot() -> None:
    """The trees' factors are the estimator's usual kinds (relative marginals, between
    factors, linear containers): a snapshot restores the map with the same estimate."""
    original = _bounded_run("chow_liu")
    restored = restore(capture(original))
    assert restored.graph.num_factors == original.graph.num_factors
    np.testing.assert_allclose(
        restored.trajectory("r1")["r1"], original.trajectory("r1")["r1"], atol=1e-2
    )


def test_a_tree_that_would_lose_a_direction_is_refused() -> None:
    """One row over three poses (what a landmark's three rays leave on its viewpoints)
    constrains them jointly and no pair: its tree would hold nothing (infinite KL) and
    could leave a pose unconstrained, so the graph keeps the marginal instead; a tree
    that keeps every direction is taken."""
    from graph.isam import IncrementalGraph

    graph = IncrementalGraph(SlamConfig())
    keys = [pose_key(0, k) for k in range(3)]
    rng = np.random.default_rng(2)

    def rows(on: list[int], n: int) -> gtsam.JacobianFactor:
        blocks = [b for k in on for b in (k, rng.normal(size=(n, 3)))]
        return gtsam.JacobianFactor(*blocks, np.zeros(n), gtsam.noiseModel.Unit.Create(n))

    assert graph._tree_of(rows(keys, 1), []) is None
    assert graph.sparsifications_refused == 1 and graph.sparsifications == 0
    chain = rows(keys[:2], 6)
    for key in keys[:2]:
        graph._theta.insert(key, gtsam.Pose2(float(key % 7), 0.0, 0.1))
    assert graph._tree_of(chain, []) is not None
    assert graph.sparsifications == 1
