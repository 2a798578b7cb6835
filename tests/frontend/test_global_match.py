"""Pose-free matching of features to landmark views (frontend.global_match)."""

from __future__ import annotations

import numpy as np

from frontend.features import Features
from frontend.global_match import hamming_matrix, match_without_pose


def _features(descriptors: np.ndarray) -> Features:
    n = len(descriptors)
    z = np.zeros(n)
    bearings = np.linspace(-3.0, 3.0, n)
    return Features(z, z, bearings, z, z + 0.01, z, np.zeros(n, np.int64), descriptors, True)


def _flip(rng: np.random.Generator, d: np.ndarray, bits: int) -> np.ndarray:
    """`d` (D,) uint8 with `bits` random bits flipped."""
    out = np.unpackbits(d.copy())
    idx = rng.choice(len(out), size=bits, replace=False)
    out[idx] ^= 1
    return np.packbits(out)


def test_hamming_matrix_agrees_with_counting_bits() -> None:
    rng = np.random.default_rng(0)
    for width in (32, 12):  # 64-bit words, and the byte-wise path
        a = rng.integers(0, 256, (17, width), dtype=np.uint8)
        b = rng.integers(0, 256, (23, width), dtype=np.uint8)
        ref = np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=2).sum(axis=2)
        assert np.array_equal(hamming_matrix(a, b), ref)
    assert hamming_matrix(np.full((1, 32), 255, np.uint8), np.zeros((1, 32), np.uint8))[0, 0] == 256


def test_features_find_their_landmark_among_many_without_a_pose() -> None:
    rng = np.random.default_rng(1)
    landmarks = rng.integers(0, 256, (60, 32), dtype=np.uint8)
    # Each landmark has 1-3 views, a few bits apart; features are other noisy copies of
    # 40 of them (shuffled), plus 30 features of nothing in the map.
    views = [
        np.stack([_flip(rng, lm, 8) for _ in range(int(rng.integers(1, 4)))]) for lm in landmarks
    ]
    seen = rng.permutation(60)[:40]
    feats = np.vstack(
        [
            np.stack([_flip(rng, landmarks[i], 10) for i in seen]),
            rng.integers(0, 256, (30, 32), dtype=np.uint8),
        ]
    )
    found = match_without_pose(_features(feats), views, max_distance=45, ratio=0.7)
    assert len(found) >= 38
    assert np.array_equal(found.landmark_index, seen[found.feature_index])
    assert np.all(found.feature_index < 40), "no feature of nothing is matched"
    assert np.all(np.diff(found.distance) >= 0) and np.all(
        (found.quality > 0) & (found.quality <= 1)
    )
    top = match_without_pose(_features(feats), views, max_distance=45, ratio=0.7, limit=5)
    assert np.array_equal(top.feature_index, found.feature_index[:5])


def test_look_alike_landmarks_are_not_matched() -> None:
    rng = np.random.default_rng(2)
    base = rng.integers(0, 256, (10, 32), dtype=np.uint8)
    twin = _flip(rng, base[3], 2)  # landmark 10 looks like landmark 3
    views = [*(v[None] for v in base), twin[None]]
    feats = np.stack([_flip(rng, d, 6) for d in base])
    found = match_without_pose(_features(feats), views, max_distance=45, ratio=0.7)
    assert 3 not in found.landmark_index.tolist() and 10 not in found.landmark_index.tolist()
    assert len(found) == 9
    # Landmarks without a view are skipped; their row numbers still name the others.
    found = match_without_pose(
        _features(base[:2].copy()),
        [np.zeros((0, 0)), *(v[None] for v in base[:3])],
        max_distance=45,
        ratio=0.7,
    )
    assert found.landmark_index.tolist() == [1, 2]
