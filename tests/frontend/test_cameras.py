"""Camera conventions: which bearing each column / ring pixel looks at."""

from __future__ import annotations

import math

import numpy as np
import pytest

from frontend.cameras import OmniCamera, PanoramaCamera, camera_from_config
from frontend.features import FeatureConfig, FeatureExtractor
from graph.angles import angle_diff
from tests.frontend._synthetic import blank, paint_corner


def test_convention_panorama_columns() -> None:
    cam = PanoramaCamera(width=1000, height=100)
    # The middle of the image (between columns 499 and 500) looks forward.
    assert cam.bearing_of_column(499.5) == pytest.approx(0.0, abs=1e-12)
    # Bearings grow to the left: a quarter from the left edge looks left (+pi/2).
    assert cam.bearing_of_column(249.5) == pytest.approx(math.pi / 2)
    assert cam.bearing_of_column(749.5) == pytest.approx(-math.pi / 2)
    # Column 0's centre is just counter-clockwise... of backwards: wrap(pi - pi/W).
    assert cam.bearing_of_column(0) == pytest.approx(math.pi - math.pi / 1000)
    # The seam between the last and first column looks backwards, +pi kept.
    assert cam.bearing_of_column(-0.5) == pytest.approx(math.pi)
    assert cam.bearing_of_column(999.5) == pytest.approx(math.pi)


def test_convention_panorama_round_trip_and_rows() -> None:
    cam = PanoramaCamera(width=2048, height=512, vfov_rad=math.radians(90))
    rng = np.random.default_rng(0)
    b = rng.uniform(-math.pi, math.pi, 200)
    back = cam.bearing_of_column(cam.column_of_bearing(b))
    assert np.max(np.abs(np.vectorize(angle_diff)(back, b))) < 1e-9
    assert cam.elevation_of_row(255.5) == pytest.approx(0.0)
    assert cam.elevation_of_row(-0.5) == pytest.approx(math.radians(45))
    assert cam.row_of_elevation(cam.elevation_of_row(100.25)) == pytest.approx(100.25)


@pytest.mark.parametrize("bearing_deg", [-150.0, -90.0, -20.0, 0.0, 35.0, 90.0, 170.0])
def test_convention_panorama_feature_at_known_bearing(bearing_deg: float) -> None:
    """A corner painted at a known bearing is detected at that bearing."""
    cam = PanoramaCamera(width=1024, height=256)
    image = blank(256, 1024)
    # The corner sits on the pixel boundary left of `column`: u = column - 0.5.
    column = round(float(cam.column_of_bearing(math.radians(bearing_deg))) + 0.5)
    paint_corner(image, column, 120)
    feats = FeatureExtractor(cam, FeatureConfig(threads=1)).extract(image)
    expected = float(cam.bearing_of_column(column - 0.5))
    near = [b for b, v in zip(feats.bearing_rad, feats.v, strict=True) if abs(v - 119.5) < 2.0]
    errors = [abs(angle_diff(b, expected)) for b in near]
    assert errors and min(errors) < cam.rad_per_px, "corner not found at its bearing"


def _ring_with_blob(cam: OmniCamera, image_angle: float, radius: float) -> np.ndarray:
    image = np.zeros((cam.height, cam.width), dtype=np.uint8)
    cx, cy = cam.centre_xy
    x = cx + radius * math.cos(image_angle) - 0.5
    y = cy - radius * math.sin(image_angle) - 0.5
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width]
    image[(xs - x) ** 2 + (ys - y) ** 2 <= 36] = 255
    return image


def _bearing_of_bright_columns(cam: OmniCamera, ring: np.ndarray) -> float:
    pano = cam.unwrap(ring)
    weight = pano.astype(np.float64).sum(axis=0)
    b = cam.panorama.bearing_of_column(np.arange(pano.shape[1]))
    return math.atan2(float(weight @ np.sin(b)), float(weight @ np.cos(b)))


@pytest.mark.parametrize(
    ("forward_deg", "mirrored", "image_angle_deg", "bearing_deg"),
    [
        (0.0, False, 90.0, 90.0),  # straight up in the picture, CCW: to the left
        (0.0, True, 90.0, -90.0),  # mirrored: to the right
        (90.0, False, 90.0, 0.0),  # "up" is forward
        (90.0, False, 180.0, 90.0),
        (-45.0, True, 0.0, -45.0),
        (0.0, False, 180.0, 180.0),  # backwards, across the panorama's seam
    ],
)
def test_convention_omni_blob_at_known_image_angle(
    forward_deg: float, mirrored: bool, image_angle_deg: float, bearing_deg: float
) -> None:
    cam = OmniCamera(
        width=400,
        height=400,
        centre_xy=(200.0, 200.0),
        inner_radius_px=40.0,
        outer_radius_px=190.0,
        forward_rad=math.radians(forward_deg),
        mirrored=mirrored,
        pano_width=720,
        pano_height=120,
    )
    ring = _ring_with_blob(cam, math.radians(image_angle_deg), 120.0)
    got = _bearing_of_bright_columns(cam, ring)
    assert abs(angle_diff(got, math.radians(bearing_deg))) < math.radians(0.5)
    # Pixel -> bearing agrees with the unwrapping.
    x = 200 + 120 * math.cos(math.radians(image_angle_deg)) - 0.5
    y = 200 - 120 * math.sin(math.radians(image_angle_deg)) - 0.5
    assert abs(angle_diff(float(cam.bearing_of_pixel(x, y)), math.radians(bearing_deg))) < 1e-9


def test_omni_outer_radius_is_the_top_row_and_maps_are_cached() -> None:
    cam = OmniCamera(400, 400, (200.0, 200.0), 40.0, 190.0, pano_width=720, pano_height=120)
    mx, my = cam.unwrap_maps()
    assert cam.unwrap_maps()[0] is mx
    r_top = math.hypot(mx[0, 0] + 0.5 - 200, my[0, 0] + 0.5 - 200)
    r_bottom = math.hypot(mx[-1, 0] + 0.5 - 200, my[-1, 0] + 0.5 - 200)
    assert r_top > 180 and r_bottom < 50


def test_camera_config_round_trip() -> None:
    omni = OmniCamera(400, 300, (200.0, 150.0), 30.0, 140.0, 0.5, True, 720, 120)
    again = camera_from_config(omni.as_config())
    assert again.as_config() == omni.as_config()
    pano = PanoramaCamera(1024, 256)
    assert camera_from_config(pano.as_config()) == pano
    with pytest.raises(ValueError, match="unknown camera model"):
        camera_from_config({"model": "fisheye"})
