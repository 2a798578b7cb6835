"""Appearance signatures: yaw from the column shift, lighting invariance, place ranking."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from frontend.appearance import AppearanceIndex, SignatureConfig, rotation_between, signature
from frontend.cameras import PanoramaCamera
from graph.angles import wrap_angle
from service.offline.datasets.render import render_panorama
from tests.frontend._synthetic import small_world

CAMERA = PanoramaCamera(width=1024, height=256)
WORLD = small_world()
PLACES = [(1.5, 1.5), (4.5, 3.0), (3.0, 4.5), (8.0, 2.0), (10.5, 4.0)]


def _pano(x: float, y: float, theta: float) -> np.ndarray:
    return render_panorama(WORLD, (x, y, theta), CAMERA)[0]


@pytest.fixture(scope="module")
def index() -> AppearanceIndex:
    idx = AppearanceIndex()
    for x, y in PLACES:
        idx.add(signature(_pano(x, y, 0.0)))
    return idx


@pytest.mark.parametrize("delta_deg", [0.0, 37.0, 90.0, 179.0, -120.0])
def test_convention_yaw_offset_is_query_minus_place(index, delta_deg: float) -> None:
    delta = math.radians(delta_deg)
    x, y = PLACES[1]
    found = index.match(signature(_pano(x, y, delta)))
    assert int(found.order[0]) == 1
    assert found.scores[1] > 0.95
    step = 2 * math.pi / SignatureConfig().columns
    assert abs(wrap_angle(found.yaw_offsets_rad[1] - delta)) <= step


@pytest.mark.parametrize(("gain", "gamma"), [(0.5, 1.0), (1.0, 0.6), (1.4, 1.5)])
def test_lighting_changes_keep_the_place_first(index, gain: float, gamma: float) -> None:
    x, y = PLACES[2]
    image = _pano(x + 0.1, y - 0.1, 2.0).astype(np.float64)
    lit = np.clip(255.0 * gain * (image / 255.0) ** gamma, 0, 255).astype(np.uint8)
    found = index.match(signature(lit))
    assert int(found.order[0]) == 2
    assert found.scores[2] - np.delete(found.scores, 2).max() > 0.1


def test_signature_is_normalised_per_band_and_refuses_bad_input() -> None:
    sig = signature(_pano(*PLACES[0], 0.3))
    assert sig.shape == (8, 256) and sig.dtype == np.float32
    np.testing.assert_allclose(sig.mean(axis=1), 0.0, atol=1e-4)
    np.testing.assert_allclose(sig.std(axis=1), 1.0, atol=1e-3)
    flat = signature(np.full((64, 512), 90, dtype=np.uint8))
    assert not flat.any()
    with pytest.raises(ValueError):
        signature(np.zeros((64, 100), dtype=np.uint8))
    with pytest.raises(ValueError):
        AppearanceIndex().add(np.zeros((4, 256), dtype=np.float32))


@pytest.mark.parametrize("delta_deg", [0.0, 3.3, 37.0, 90.0, -90.0, 179.0])
def test_convention_compass_is_current_minus_previous_to_a_fraction_of_a_column(
    delta_deg: float,
) -> None:
    x, y = PLACES[2]
    theta = 0.4
    yaw, score = rotation_between(
        signature(_pano(x, y, theta)), signature(_pano(x, y, theta + math.radians(delta_deg)))
    )
    assert score > 0.95
    column = 360.0 / SignatureConfig().columns
    assert abs(math.degrees(wrap_angle(yaw - math.radians(delta_deg)))) < 0.5 * column


def test_compass_after_a_step_forward_and_a_turn_and_refusing_mixed_shapes() -> None:
    # 10 cm of parallax on top of a 90-degree turn: still the turn, within a degree.
    yaw, score = rotation_between(
        signature(_pano(3.0, 4.5, 0.0)), signature(_pano(3.1, 4.5, math.pi / 2))
    )
    assert score > 0.8
    assert abs(math.degrees(wrap_angle(yaw - math.pi / 2))) < 1.0
    with pytest.raises(ValueError, match="shapes"):
        rotation_between(np.zeros((8, 256), np.float32), np.zeros((8, 128), np.float32))


def test_signature_lookup_table_equals_log1p() -> None:
    """The signature's log via a lookup table is exactly float32 log1p of each pixel."""
    rng = np.random.default_rng(5)
    pano = rng.integers(0, 256, size=(64, 512), dtype=np.uint8)
    log_i = np.log1p(pano.astype(np.float32))
    small = cv2.resize(log_i, (256, 8), interpolation=cv2.INTER_AREA)
    small -= small.mean(axis=1, keepdims=True)
    expected = small / small.std(axis=1, keepdims=True)
    np.testing.assert_array_equal(signature(pano), expected)
    with pytest.raises(ValueError, match="8-bit"):
        signature(pano.astype(np.float32))
