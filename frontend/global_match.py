"""Matching a panorama's features to the map's landmarks without a pose prior.

A robot that does not know where it is (its first frame without an initial pose, or
after it was carried elsewhere) cannot gate its features by predicted bearings. Here
every feature is compared with every stored view of every landmark by descriptor
alone: a landmark's distance to a feature is the smallest over its views; a match is
kept when it is the feature's best landmark, that landmark's best feature (mutual),
within `max_distance`, and clearly better than the feature's second-best landmark and
the landmark's second-best feature (ratio test, as frontend.association does). Poster
corners look alike, so some matches are wrong: the particle filter that weighs them
has a uniform part in its sensor model for that.

Each match's quality in [0, 1] falls linearly with its descriptor distance (1 at 0,
0 at `max_distance`), for the filter's per-landmark weighting.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from frontend.features import Features

__all__ = ["GlobalMatch", "hamming_matrix", "match_without_pose"]

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class GlobalMatch:
    """``(K,)`` matched feature indices, the landmark (row of the caller's list) each
    matched, the descriptor distance and the quality in [0, 1]; best quality first."""

    feature_index: IntArray
    landmark_index: IntArray
    distance: FloatArray
    quality: FloatArray

    def __len__(self) -> int:
        return len(self.feature_index)


def _empty() -> GlobalMatch:
    z = np.zeros(0, dtype=np.int64)
    return GlobalMatch(z, z.copy(), np.zeros(0), np.zeros(0))


def hamming_matrix(a: NDArray[np.generic], b: NDArray[np.generic]) -> NDArray[np.uint16]:
    """``(A, B)`` Hamming distances (bits) between the rows of two binary descriptor
    arrays ``(A, D)``, ``(B, D)`` of uint8 (64 bits at a time when D is a multiple of 8)."""
    a8 = np.ascontiguousarray(a, dtype=np.uint8)
    b8 = np.ascontiguousarray(b, dtype=np.uint8)
    out = np.zeros((len(a8), len(b8)), dtype=np.uint16)
    if a8.shape[1] % 8 == 0:
        a8, b8 = a8.view(np.uint64), b8.view(np.uint64)
    for j in range(a8.shape[1]):
        out += np.bitwise_count(a8[:, j : j + 1] ^ b8[None, :, j])
    return out


def match_without_pose(
    features: Features,
    views: Sequence[NDArray[np.generic]],
    *,
    max_distance: float,
    ratio: float,
    limit: int | None = None,
) -> GlobalMatch:
    """Match `features` to landmarks whose stored views are ``views[l]`` ``(V_l, D)``
    (same descriptor type as the features), without a pose prior (module docstring).

    `max_distance`: Hamming bits for binary descriptors, L2 otherwise; `limit`: keep at
    most this many matches (best quality first)."""
    rows = [np.asarray(v) for v in views if len(v)]
    owners = [i for i, v in enumerate(views) if len(v)]
    if not rows or len(features) == 0:
        return _empty()
    stacked = np.concatenate(rows, axis=0)
    counts = np.array([len(v) for v in rows], dtype=np.int64)
    query = features.descriptors
    if features.binary:
        dist = hamming_matrix(query, stacked)
    else:
        q = np.asarray(query, dtype=np.float32)
        v = np.asarray(stacked, dtype=np.float32)
        sq = (q * q).sum(1)[:, None] + (v * v).sum(1)[None, :] - 2.0 * (q @ v.T)
        dist = np.sqrt(np.maximum(sq, 0.0))
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    d = np.minimum.reduceat(np.asarray(dist, dtype=np.float64), starts, axis=1)  # (F, L)
    n_f, n_l = d.shape
    if n_l < 2 or n_f < 2:
        return _empty()  # no second best on one side: the ratio test cannot speak
    part_f = np.partition(d, 1, axis=1)  # per feature: best, second-best landmark
    part_l = np.partition(d, 1, axis=0)  # per landmark: best, second-best feature
    best_l = np.argmin(d, axis=1)  # (F,) each feature's best landmark
    best_f = np.argmin(d, axis=0)  # (L,) each landmark's best feature
    f_idx = np.arange(n_f)
    best = d[f_idx, best_l]
    ok = (
        (best <= max_distance)
        & (best < ratio * part_f[:, 1])
        & (best_f[best_l] == f_idx)
        & (best < ratio * part_l[1, best_l])
    )
    fi = f_idx[ok]
    li = best_l[ok]
    dd = best[ok]
    order = np.argsort(dd, kind="stable")
    if limit is not None:
        order = order[:limit]
    fi, li, dd = fi[order], li[order], dd[order]
    owner = np.asarray(owners, dtype=np.int64)[li]
    quality = np.clip(1.0 - dd / max_distance, 0.0, 1.0)
    return GlobalMatch(fi.astype(np.int64), owner, dd, quality)
