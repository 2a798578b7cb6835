"""Chow-Liu tree sparsification of a dense Gaussian marginal (sparse GLC).

Marginalising a variable leaves one dense Gaussian over its Markov blanket (see
graph.isam). `chow_liu_tree` replaces it by the tree-structured Gaussian closest to
it in KL(exact || tree) (Chow & Liu 1968; as used for node removal by
Carlevaris-Bianco, Kaess & Eustice, "Generic Node Removal for Factor-Graph SLAM",
T-RO 2014): the maximum spanning tree of the pairwise mutual information between the
blanket's variables, and per tree edge the conditional of the child given its
parent, p(x) ~ p(x_root) prod p(x_child | x_parent). Each conditional is one binary
linear factor; the root's marginal is one unary factor.

Convention: a blanket is a list of variables with dimensions `dims` (3 for a Pose2,
2 for a Point2) in the column order of the information matrix. A Gaussian is given
by its *augmented* information ``[[H, g], [g^T, f]] = [A | b]^T [A | b]`` of the
error ``|A x - b|^2`` (GTSAM's ``augmentedInformation``), shape (n + 1, n + 1).

Rank deficiency. A marginal of bearing-only and relative measurements often has no
covariance: it carries no absolute part (a rigid motion of the blanket is free, the
gauge), and a landmark's rays constrain its viewpoints jointly, not pairwise (two rays
always meet). GLC takes the target information's pseudo-inverse on its observable
subspace. Here:

* the tree's *factors* are exact limits for a vanishing prior: the pairwise and unary
  marginals are generalised Schur complements ``H_aa - H_ab H_bb^+ H_ba`` of the
  augmented information (the limit of the proper marginals as a prior eps*I on every
  variable goes to 0). A direction the marginal does not observe (the gauge, a lone
  ray) stays unobserved in every factor: a gauge-free marginal gives a gauge-free
  tree, with no root factor, and nothing absolute is invented;
* the tree's *structure* (which edges) needs mutual information, which needs a
  covariance: it is computed with a pseudo-prior ``eps * mean(diag H)`` on every
  variable added (`_PSEUDO_PRIOR`). The pseudo-prior only chooses edges; it is not in
  any factor.

When the marginal already is a tree (a chain of relative-pose constraints, say), the
tree found is that tree and its joint equals the marginal exactly; otherwise the
tree keeps each edge's pairwise marginal and loses the rest, which `kl_divergence`
measures.
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

_PSEUDO_PRIOR = 1e-6
"""Pseudo-prior on every variable, relative to the mean diagonal of the information,
under which mutual information is computed (tree structure only)."""
_NULL_TOL = 1e-8
"""A set of variables sees a direction of the null space when its rows of the null
space's orthonormal basis have a singular value above this (see `_Marginals`)."""
_RANK_TOL = 1e-10
"""Eigenvalues below this fraction of the largest count as zero (pseudo-inverses,
square roots and observable subspaces)."""


@dataclass(frozen=True)
class TreeFactor:
    """One factor of a Chow-Liu tree: ``|sum_i A_i x_{vars[i]} - b|^2``.

    `vars`: (child, parent) blanket indices of an edge, or (root,) for the root's
    marginal. `blocks`: the A_i, each (rows, dims[var]). Rows are the factor's rank (a
    rank-0 factor is never returned)."""

    vars: tuple[int, ...]
    blocks: tuple[FloatArray, ...]
    b: FloatArray


@dataclass(frozen=True)
class ChowLiuTree:
    """A Chow-Liu tree approximation over a blanket of `len(dims)` variables.

    `edges`: (child, parent) blanket indices, n - 1 of them; `root`: the root's index;
    `factors`: the non-empty factors (a conditional per edge, the root's marginal);
    `information`: (n + 1, n + 1) augmented information of the tree's joint;
    `mutual_information`: (n, n) pairwise mutual information (nats) the tree was
    chosen by; `kl`: KL(marginal || tree) in nats (see `kl_divergence`; inf when the
    tree loses a direction the marginal observes)."""

    dims: tuple[int, ...]
    root: int
    edges: tuple[tuple[int, int], ...]
    factors: tuple[TreeFactor, ...]
    information: FloatArray
    mutual_information: FloatArray
    kl: float


def _offsets(dims: Sequence[int]) -> FloatArray:
    return np.concatenate([[0], np.cumsum(dims)]).astype(int)


def _columns(offsets: FloatArray, variables: Sequence[int]) -> list[int]:
    return [c for v in variables for c in range(int(offsets[v]), int(offsets[v + 1]))]


def _psd_pinv(m: FloatArray) -> FloatArray:
    """Pseudo-inverse of a symmetric positive semi-definite matrix."""
    if m.size == 0:
        return m.copy()
    w, v = np.linalg.eigh(0.5 * (m + m.T))
    keep = w > _RANK_TOL * max(float(w[-1]), 1e-300)
    return (v[:, keep] / w[keep]) @ v[:, keep].T


def marginal_information(augmented: FloatArray, keep: Sequence[int]) -> FloatArray:
    """Augmented information of the columns `keep` (plus the constant, last) with every
    other column eliminated: the generalised Schur complement, exact also when the
    eliminated block is singular (the limit of a vanishing prior on it)."""
    n = augmented.shape[0] - 1
    kept = [*keep, n]
    gone = sorted(set(range(n)) - set(keep))
    aa = augmented[np.ix_(kept, kept)]
    if not gone:
        return 0.5 * (aa + aa.T)
    ab = augmented[np.ix_(kept, gone)]
    out = aa - ab @ _psd_pinv(augmented[np.ix_(gone, gone)]) @ ab.T
    return 0.5 * (out + out.T)


def _square_root(augmented: FloatArray) -> tuple[FloatArray, FloatArray]:
    """[A | b] with [A | b]^T [A | b] = `augmented` (rows: its rank)."""
    w, v = np.linalg.eigh(0.5 * (augmented + augmented.T))
    keep = w > _RANK_TOL * max(float(w[-1]), 1e-300)
    root = np.sqrt(w[keep])[:, None] * v[:, keep].T
    return root[:, :-1], root[:, -1]


def mutual_information(information: FloatArray, dims: Sequence[int]) -> FloatArray:
    """(n, n) mutual information (nats) between every pair of the blanket's variables,
    of the Gaussian with (non-augmented) `information` plus a pseudo-prior (see the
    module docstring); the diagonal is 0."""
    w, v = np.linalg.eigh(0.5 * (information + information.T))
    return _pairwise_mutual_information(_pseudo_covariance(information, w, v), dims)


def _pseudo_covariance(information: FloatArray, w: FloatArray, v: FloatArray) -> FloatArray:
    """The covariance of `information` (eigenpairs `w`, `v`) plus the pseudo-prior."""
    scale = float(np.mean(np.diag(information))) if information.size else 1.0
    return np.asarray((v / (w + _PSEUDO_PRIOR * max(scale, 1e-12))) @ v.T, dtype=np.float64)


class _Marginals:
    """Exact marginals of small sets of a blanket's variables from one eigen-decomposition
    of the whole information H, instead of one generalised Schur complement (one
    pseudo-inverse of nearly all of H) per set.

    With a prior eps*I on every variable, the covariance is ``H^+ + N N^T / eps`` (N an
    orthonormal basis of H's null space), so a set `a`'s covariance is ``A + N_a N_a^T /
    eps`` (A the set's block of H^+, N_a the set's rows of N); as eps -> 0 its inverse
    tends to ``Q (Q^T A Q)^-1 Q^T``, Q an orthonormal basis of the complement of N_a's
    column space: the same limit as `marginal_information` (Q^T A Q is positive
    definite: a direction of Q with Q^T A Q = 0 would lie in N). The linear term is the
    marginal times the set's part of the minimum-norm mean H^+ g, and the constant
    keeps the block's residual ``f - g^T H^+ g``."""

    def __init__(self, augmented: FloatArray) -> None:
        n = augmented.shape[0] - 1
        h = augmented[:n, :n]
        w, v = np.linalg.eigh(h)
        keep = w > _RANK_TOL * max(float(w[-1]), 1e-300) if n else np.zeros(0, dtype=bool)
        self.eigen = (w, v)
        self._pinv = (v[:, keep] / w[keep]) @ v[:, keep].T
        self._null = v[:, ~keep]
        self._mean = self._pinv @ augmented[:n, n]
        self._residual = float(augmented[n, n] - augmented[:n, n] @ self._mean)

    def of(self, columns: Sequence[int]) -> FloatArray:
        """Augmented information of `columns` with every other column eliminated."""
        cols = list(columns)
        k = len(cols)
        a = self._pinv[np.ix_(cols, cols)]
        null = self._null[cols]
        if null.shape[1]:
            u, s, _ = np.linalg.svd(null, full_matrices=True)
            q = u[:, int(np.sum(s > _NULL_TOL)) :]
        else:
            q = np.eye(k)
        m = q @ np.linalg.solve(q.T @ a @ q, q.T) if q.shape[1] else np.zeros((k, k))
        m = 0.5 * (m + m.T)
        mean = self._mean[cols]
        g = m @ mean
        out = np.empty((k + 1, k + 1))
        out[:k, :k] = m
        out[:k, k] = out[k, :k] = g
        out[k, k] = float(mean @ g) + max(self._residual, 0.0)
        return out


def _padded_index(dims: Sequence[int]) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """(n, 3) column indices of every variable, padded to 3 (a Point2's third column
    repeats its first), and the (n, 3) mask of the real ones."""
    o = _offsets(dims)
    index = np.zeros((len(dims), 3), dtype=np.int64)
    real = np.zeros((len(dims), 3), dtype=bool)
    for i, d in enumerate(dims):
        index[i, :d] = np.arange(o[i], o[i] + d)
        index[i, d:] = o[i]
        real[i, :d] = True
    return index, real


def _logdets(cov: FloatArray, index: NDArray[np.int64], real: NDArray[np.bool_]) -> FloatArray:
    """log|S_b| of every block b of `cov` whose columns are the rows of `index`
    (..., k), in one batched call; padded columns (not `real`) get the identity, which
    leaves the determinant."""
    blocks = cov[index[..., :, None], index[..., None, :]]
    pad = ~(real[..., :, None] & real[..., None, :])
    eye = np.eye(index.shape[-1], dtype=bool)
    return np.asarray(np.linalg.slogdet(np.where(pad, eye, blocks))[1], dtype=np.float64)


def _pairwise_mutual_information(cov: FloatArray, dims: Sequence[int]) -> FloatArray:
    """I(x_i; x_j) = 0.5 (log|S_ii| + log|S_jj| - log|S_ij,ij|) for every pair i < j,
    from one covariance (each variable's columns padded to 3, see `_padded_index`)."""
    n = len(dims)
    out = np.zeros((n, n))
    if n < 2:
        return out
    index, real = _padded_index(dims)
    single = _logdets(cov, index, real)
    i, j = np.triu_indices(n, 1)
    joint = _logdets(
        cov,
        np.concatenate([index[i], index[j]], axis=1),
        np.concatenate([real[i], real[j]], axis=1),
    )
    out[i, j] = np.maximum(0.5 * (single[i] + single[j] - joint), 0.0)
    return out + out.T


def maximum_spanning_tree(weights: FloatArray, root: int = 0) -> list[tuple[int, int]]:
    """(child, parent) edges of a maximum spanning tree of the complete graph with
    symmetric `weights` (Prim's algorithm from `root`; ties go to the lower index)."""
    n = weights.shape[0]
    if n == 0:
        return []
    inside = np.zeros(n, dtype=bool)
    inside[root] = True
    best = weights[root].astype(np.float64).copy()
    parent = np.full(n, root)
    edges: list[tuple[int, int]] = []
    for _ in range(n - 1):
        candidates = np.where(inside, -np.inf, best)
        child = int(np.argmax(candidates))
        edges.append((child, int(parent[child])))
        inside[child] = True
        closer = ~inside & (weights[child] > best)
        best[closer] = weights[child][closer]
        parent[closer] = child
    return edges


def _factor(
    augmented: FloatArray, variables: tuple[int, ...], dims: Sequence[int], scale: float
) -> TreeFactor | None:
    """The factor of a tree's augmented information block, or None if it carries no
    information on its variables (rows of A below 1e-6 * `scale`, a square root of the
    marginal's largest diagonal: what is left is a constant, e.g. a gauge-free root's)."""
    a, b = _square_root(augmented)
    informative = np.abs(a).max(axis=1, initial=0.0) > 1e-6 * scale
    a, b = a[informative], b[informative]
    if a.shape[0] == 0:
        return None
    o = np.concatenate([[0], np.cumsum([dims[v] for v in variables])]).astype(int)
    blocks = tuple(a[:, o[i] : o[i + 1]] for i in range(len(variables)))
    return TreeFactor(variables, blocks, b)


def chow_liu_tree(augmented: FloatArray, dims: Sequence[int], *, root: int = 0) -> ChowLiuTree:
    """The Chow-Liu tree of the Gaussian with `augmented` information ((n + 1, n + 1),
    see the module docstring) over variables of `dims`, rooted at `root`.

    Per edge (child c, parent p) the conditional's augmented information is the pair's
    marginal less the parent's: ``M_{cp} - [0, 0; 0, M_p]``, positive semi-definite, and
    the root's factor is its marginal ``M_root``; their sum is the tree's joint."""
    dims = tuple(int(d) for d in dims)
    o = _offsets(dims)
    augmented = 0.5 * (augmented + augmented.T)
    scale = math.sqrt(max(float(np.max(np.diag(augmented)[:-1], initial=0.0)), 1e-300))
    marginals = _Marginals(augmented)
    mi = _pairwise_mutual_information(
        _pseudo_covariance(augmented[:-1, :-1], *marginals.eigen), dims
    )
    edges = maximum_spanning_tree(mi, root)
    size = int(o[-1])
    joint = np.zeros((size + 1, size + 1))

    def add(variables: tuple[int, ...], block: FloatArray) -> None:
        cols = [*_columns(o, variables), size]
        joint[np.ix_(cols, cols)] += block

    factors: list[TreeFactor] = []
    unary: dict[int, FloatArray] = {}

    def marginal_of(v: int) -> FloatArray:
        if v not in unary:
            unary[v] = marginals.of(_columns(o, (v,)))
        return unary[v]

    root_info = marginal_of(root)
    add((root,), root_info)
    factor = _factor(root_info, (root,), dims, scale)
    if factor is not None:
        factors.append(factor)
    for child, parent in edges:
        pair = marginals.of(_columns(o, (child, parent)))
        conditional = pair.copy()
        rows = [*range(dims[child], dims[child] + dims[parent]), dims[child] + dims[parent]]
        conditional[np.ix_(rows, rows)] -= marginal_of(parent)
        add((child, parent), conditional)
        factor = _factor(conditional, (child, parent), dims, scale)
        if factor is not None:
            factors.append(factor)
    kl = _kl_from_eigen(*marginals.eigen, joint[:-1, :-1])
    return ChowLiuTree(dims, root, tuple(edges), tuple(factors), joint, mi, kl)


def kl_divergence(exact: FloatArray, approx: FloatArray) -> float:
    """KL(exact || approx) in nats between two zero-mean Gaussians given by their
    (non-augmented) information matrices, (n, n) each:
    ``0.5 * (tr(L S) - r - log det(L S))`` with S the exact covariance and L the
    approximation's information (equal means: a Chow-Liu tree keeps the mean).

    Gauge-free or otherwise rank-deficient `exact`: on its observable subspace (the
    span of its eigenvectors above _RANK_TOL of the largest; r its dimension), where S
    exists. An approximation that invents information outside that subspace is not
    penalised there; one that loses a direction of it has no finite divergence: inf."""
    w, v = np.linalg.eigh(0.5 * (exact + exact.T))
    return _kl_from_eigen(w, v, approx)


def _kl_from_eigen(w: FloatArray, v: FloatArray, approx: FloatArray) -> float:
    """`kl_divergence` given the exact information's eigenpairs `w`, `v`."""
    if not len(w):
        return 0.0
    keep = w > _RANK_TOL * max(float(w[-1]), 1e-300)
    r = int(keep.sum())
    if r == 0:
        return 0.0
    # Whitened by the exact information: the eigenvalues of S^1/2 L S^1/2.
    whiten = v[:, keep] / np.sqrt(w[keep])
    ratio = np.linalg.eigvalsh(whiten.T @ (0.5 * (approx + approx.T)) @ whiten)
    if ratio[0] <= _RANK_TOL * max(float(ratio[-1]), 1.0):
        return math.inf
    return max(0.5 * float(np.sum(ratio - 1.0 - np.log(ratio))), 0.0)


def tree_factors(factor: gtsam.GaussianFactor) -> tuple[list[gtsam.JacobianFactor], ChowLiuTree]:
    """The Chow-Liu tree of a linear `factor` over Pose2 and Point2 keys, as one
    ``JacobianFactor`` (unit noise) per non-empty tree factor, and the tree itself
    (blanket indices follow ``factor.keys()``; rooted at the first key)."""
    keys = list(factor.keys())
    dims = [2 if is_landmark_key(k) else 3 for k in keys]
    augmented = np.asarray(factor.augmentedInformation(), dtype=np.float64)
    tree = chow_liu_tree(augmented, dims)
    out: list[gtsam.JacobianFactor] = []
    for f in tree.factors:
        model = gtsam.noiseModel.Unit.Create(len(f.b))
        if len(f.vars) == 1:
            out.append(gtsam.JacobianFactor(keys[f.vars[0]], f.blocks[0], f.b, model))
        else:
            c, p = f.vars
            out.append(gtsam.JacobianFactor(keys[c], f.blocks[0], keys[p], f.blocks[1], f.b, model))
    return out, tree
