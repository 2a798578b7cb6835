"""Upright descriptors: a panorama has no roll, so a poster's corners must not look alike."""

from __future__ import annotations

import numpy as np

from frontend.association import _distances
from frontend.cameras import PanoramaCamera
from frontend.features import FeatureConfig, FeatureExtractor, Features
from tests.frontend import _synthetic as synthetic

CAMERA = PanoramaCamera(1024, 256)


def _poster(shift: int = 0, seed: int = 0) -> np.ndarray:
    """A bright rectangle on a grey wall with mild noise (its own per `seed`), the whole
    view turned right by `shift` px."""
    image = synthetic.blank(256, 1024)
    rng = np.random.default_rng(seed)
    image[:] = np.clip(90 + rng.normal(0, 3, image.shape), 0, 255).astype(np.uint8)
    image[90:170, 400:520] = 220
    return np.roll(image, shift, axis=1)


def _corners(feats: Features, shift: int = 0) -> dict[str, int]:
    """Index of the feature nearest each of the rectangle's four corners (within 3 px)."""
    out = {}
    for name, (u, v) in {
        "top_left": (400, 90),
        "top_right": (520, 90),
        "bottom_left": (400, 170),
        "bottom_right": (520, 170),
    }.items():
        d = np.hypot(feats.u - (u + shift - 0.5), feats.v - (v - 0.5))
        assert d.min() < 3.0, f"{name} not detected"
        out[name] = int(np.argmin(d))
    return out


def _distance(a: Features, i: int, b: Features, j: int) -> float:
    return float(_distances(a.descriptors[i : i + 1], b.descriptors[j : j + 1], True)[0])


def test_upright_descriptors_tell_a_rectangles_corners_apart() -> None:
    nearest_other = {}
    for upright in (True, False):
        extractor = FeatureExtractor(CAMERA, FeatureConfig(threads=1, upright=upright))
        # Another view: turned by 7 px, the wall's noise drawn anew (a new exposure).
        a, b = extractor.extract(_poster()), extractor.extract(_poster(shift=7, seed=1))
        ca, cb = _corners(a), _corners(b, shift=7)
        same = [_distance(a, ca[n], b, cb[n]) for n in ca]
        other = [_distance(a, ca[m], b, cb[n]) for m in ca for n in cb if m != n]
        nearest_other[upright] = min(other)
        if upright:
            # The same corner is within the association's max_distance (45 bits; noise
            # flips the comparisons inside flat areas), every other corner is far.
            assert max(same) <= 45 and min(other) >= 90, (same, other)
        extractor.close()
    # Orientation-invariant descriptors see the corners as rotated copies of one another.
    assert nearest_other[False] < 0.6 * nearest_other[True], nearest_other


def test_upright_descriptors_wrap_around_the_seam() -> None:
    extractor = FeatureExtractor(CAMERA, FeatureConfig(threads=1))
    image = _poster()
    rolled = np.roll(image, 1024 - 460, axis=1)  # the rectangle now straddles the seam
    a, b = extractor.extract(image), extractor.extract(rolled)
    ca = _corners(a)
    for name, i in ca.items():
        u = (a.u[i] + 1024 - 460) % 1024
        d = np.hypot(((b.u - u + 512) % 1024) - 512, b.v - a.v[i])
        j = int(np.argmin(d))
        # Matchable (within the association's 45 bits): the same pixels around it, though
        # ORB may find it on another pyramid level there.
        assert d[j] < 1.0 and _distance(a, i, b, j) <= 45, (name, d[j], _distance(a, i, b, j))
    extractor.close()
