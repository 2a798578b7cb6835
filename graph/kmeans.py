"""K-means under the L1 (Manhattan) distance, i.e. k-medians.

Hochdorfer & Schlegel cluster the mean observation positions of the landmarks
with k-means under the L1 distance. Under L1 the point that minimises the summed
distance to a cluster's members is their coordinate-wise median, not their mean,
so the centre update here is the median: k-means with L1 distance, i.e.
k-medians. Each Lloyd step (assign to the L1-nearest centre, move each centre to
the median of its members) never increases the summed L1 distance.

Conventions: points are ``(N, 2)`` positions in metres (any planar frame), the
distance between ``p`` and ``q`` is ``|px - qx| + |py - qy|`` in metres. Ties
are broken by the lowest index (a point equally near two centres joins the one
with the lower index). Randomness comes only from the ``rng`` passed in.
"""

from __future__ import annotations

import operator
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray


@dataclass(frozen=True)
class KMeansResult:
    """The clustering of ``N`` points into ``k`` clusters.

    ``labels`` (N,) int64: cluster index of each point, in ``[0, k)``.
    ``centres`` (k, 2) float64: each cluster's coordinate-wise median, metres.
    ``iterations``: Lloyd iterations run (0 when no iteration was needed).
    ``cost``: summed L1 distance of the points to their centres, metres.
    ``converged``: False only when ``max_iter`` stopped the iterations.

    ``k`` here is ``len(centres)``: the requested k clipped to the number of
    distinct points, so that no cluster is ever empty.
    """

    labels: NDArray[np.int64]
    centres: NDArray[np.float64]
    iterations: int
    cost: float
    converged: bool = True


def l1_distances(points: ArrayLike, centres: ArrayLike) -> NDArray[np.float64]:
    """L1 distance of every point to every centre: (N, 2), (k, 2) -> (N, k), metres."""
    p = np.asarray(points, dtype=np.float64)
    c = np.asarray(centres, dtype=np.float64)
    return np.abs(p[:, None, :] - c[None, :, :]).sum(axis=2)


def kmeans_l1(
    points: ArrayLike,
    k: int,
    *,
    rng: np.random.Generator,
    max_iter: int = 100,
    n_init: int = 1,
) -> KMeansResult:
    """Cluster ``(N, 2)`` points into ``k`` clusters under the L1 distance (k-medians).

    Initialisation is k-means++ with the L1 distance: the first centre is a point
    drawn uniformly, each further centre a point drawn with probability
    proportional to its L1 distance to the nearest centre chosen so far (the
    first power, matching the L1 objective). Then Lloyd iterations: assignment to
    the L1-nearest centre (ties: lowest centre index), centre update by the
    coordinate-wise median (the mean of the two middle values for an even count).
    A cluster left empty is re-seeded with the point farthest from its own centre
    (ties: lowest point index). Iterations stop when an assignment no longer
    changes, or after ``max_iter``.

    ``n_init`` runs are seeded one after the other from ``rng`` and the one with
    the lowest cost is kept (ties: the earliest); a single run can end in a poor
    local optimum that merges two far-apart groups.

    When ``k`` is at least the number of distinct points, each distinct point is
    its own cluster (duplicates share one), numbered in order of first
    occurrence, and ``rng`` is not used. Otherwise the result is a deterministic
    function of the points, ``k``, ``max_iter``, ``n_init`` and the state of ``rng``.

    Raises ValueError for ``k <= 0``, ``max_iter < 1``, ``n_init < 1``, no
    points, a shape other than ``(N, 2)`` or non-finite coordinates.
    """
    k = operator.index(k)
    if k <= 0:
        raise ValueError(f"k must be a positive number of clusters, got {k}")
    if max_iter < 1:
        raise ValueError(f"max_iter must be at least 1, got {max_iter}")
    if n_init < 1:
        raise ValueError(f"n_init must be at least 1, got {n_init}")
    pts = _as_points(points)

    uniq, first, inverse = np.unique(pts, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    if k >= len(uniq):
        order = np.argsort(first, kind="stable")  # distinct points by first occurrence
        rank = np.empty(len(order), dtype=np.int64)
        rank[order] = np.arange(len(order))
        return KMeansResult(
            labels=rank[inverse], centres=uniq[order].copy(), iterations=0, cost=0.0
        )

    best = _lloyd(pts, k, rng, max_iter)
    for _ in range(n_init - 1):
        run = _lloyd(pts, k, rng, max_iter)
        if run.cost < best.cost:
            best = run
    return best


def _lloyd(
    pts: NDArray[np.float64], k: int, rng: np.random.Generator, max_iter: int
) -> KMeansResult:
    """One seeded run; needs ``k`` at most the number of distinct points."""
    centres = _init_plus_plus(pts, k, rng)
    labels = np.full(len(pts), -1, dtype=np.int64)
    for iteration in range(1, max_iter + 1):
        new_labels, reseeded = _assign(pts, centres)
        if not reseeded and np.array_equal(new_labels, labels):
            # centres are already the medians of exactly these labels
            return _result(pts, labels, centres, iteration - 1, converged=True)
        labels = new_labels
        centres = cluster_medians(pts, labels, k)
    return _result(pts, labels, centres, max_iter, converged=False)


def _result(
    pts: NDArray[np.float64],
    labels: NDArray[np.int64],
    centres: NDArray[np.float64],
    iterations: int,
    *,
    converged: bool,
) -> KMeansResult:
    cost = float(np.abs(pts - centres[labels]).sum())
    return KMeansResult(labels, centres, iterations, cost, converged)


def cluster_medians(points: ArrayLike, labels: ArrayLike, k: int) -> NDArray[np.float64]:
    """Coordinate-wise median of each cluster: (N, 2), (N,) -> (k, 2), metres.

    Every cluster in ``[0, k)`` must have at least one member. For an even count
    the median is the mean of the two middle values (any value between them
    minimises the summed L1 distance; the midpoint is the usual choice).
    """
    pts = np.asarray(points, dtype=np.float64)
    lab = np.asarray(labels, dtype=np.int64)
    counts = np.bincount(lab, minlength=k)
    if len(counts) != k or np.any(counts == 0):
        raise ValueError("every cluster in [0, k) needs at least one member")
    starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
    lo = starts + (counts - 1) // 2
    hi = starts + counts // 2
    centres = np.empty((k, 2), dtype=np.float64)
    for axis in range(2):  # a loop over the two coordinates, not over points
        order = np.lexsort((pts[:, axis], lab))  # by cluster, then by coordinate
        values = pts[order, axis]
        centres[:, axis] = 0.5 * (values[lo] + values[hi])
    return centres


def _as_points(points: ArrayLike) -> NDArray[np.float64]:
    # "+ 0.0" turns -0.0 into +0.0 so that np.unique sees them as one point
    pts = np.asarray(points, dtype=np.float64) + 0.0
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points must have shape (N, 2), got {pts.shape}")
    if len(pts) == 0:
        raise ValueError("no points to cluster")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points must be finite")
    return pts


def _init_plus_plus(
    points: NDArray[np.float64], k: int, rng: np.random.Generator
) -> NDArray[np.float64]:
    """k-means++ seeding under L1; needs ``k`` at most the number of distinct points."""
    n = len(points)
    chosen = np.empty(k, dtype=np.intp)
    chosen[0] = rng.integers(n)
    nearest = np.abs(points - points[chosen[0]]).sum(axis=1)
    for j in range(1, k):  # a loop over centres
        # fewer than k <= distinct centres chosen, so some point is at distance > 0
        cumulative = np.cumsum(nearest)
        u = rng.random() * cumulative[-1]
        i = int(np.searchsorted(cumulative, u, side="right"))
        i = min(i, int(np.flatnonzero(nearest > 0)[-1]))  # guard against rounding at the top
        chosen[j] = i
        nearest = np.minimum(nearest, np.abs(points - points[i]).sum(axis=1))
    return points[chosen].copy()


def _assign(
    points: NDArray[np.float64], centres: NDArray[np.float64]
) -> tuple[NDArray[np.int64], bool]:
    """Assign to the L1-nearest centre, re-seeding empty clusters (``centres`` in place).

    A re-seeded centre sits on a point whose nearest centre is at a distance
    > 0, so that point now joins it and no other centre sits on it; a cluster
    whose centre is one of its own points can therefore never be emptied by a
    later re-seed, and each re-seed adds one such cluster: at most k re-seeds.
    """
    n, k = len(points), len(centres)
    d = l1_distances(points, centres)
    labels = np.argmin(d, axis=1).astype(np.int64)  # argmin: lowest index on ties
    reseeded = False
    for _ in range(k + 1):
        empty = np.flatnonzero(np.bincount(labels, minlength=k) == 0)
        if empty.size == 0:
            break
        j = int(empty[0])
        own = d[np.arange(n), labels]
        i = int(np.argmax(own))  # farthest from its centre; argmax: lowest index on ties
        centres[j] = points[i]
        d[:, j] = np.abs(points - points[i]).sum(axis=1)
        labels = np.argmin(d, axis=1).astype(np.int64)
        reseeded = True
    return labels, reseeded
