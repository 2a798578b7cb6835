"""The panorama's seam: a feature straddling it is found once, with the right bearing."""

from __future__ import annotations

import math

import numpy as np

from frontend.cameras import PanoramaCamera
from frontend.features import FeatureConfig, FeatureExtractor
from graph.angles import angle_diff
from service.offline.datasets.render import render_panorama
from tests.frontend._synthetic import blank, paint_corner, small_world


def test_corner_on_the_seam_is_found_once_at_bearing_pi() -> None:
    cam = PanoramaCamera(width=1024, height=256)
    image = blank(256, 1024)
    # A square spanning columns 1014..1023 and 0..13: its top-left corner lies 10 px
    # left of the seam, its top-right corner 14 px right of it, both inside the pad.
    paint_corner(image, 1014, 100, size=24)
    feats = FeatureExtractor(cam, FeatureConfig(threads=2, bands=4)).extract(image)
    for column in (1014, 1038):
        expected = float(cam.bearing_of_column(column - 0.5))
        hits = [
            b
            for b, v in zip(feats.bearing_rad, feats.v, strict=True)
            if abs(v - 99.5) < 2.0 and abs(angle_diff(b, expected)) < 3 * cam.rad_per_px
        ]
        assert len(hits) == 1, f"corner at column {column % 1024}: {len(hits)} detections"
        assert abs(angle_diff(hits[0], expected)) < cam.rad_per_px


def test_rolled_panorama_gives_the_same_features_turned() -> None:
    """Turning the robot by half a turn rolls the panorama: bearings shift by pi."""
    cam = PanoramaCamera(width=1024, height=256)
    image, _ = render_panorama(small_world(), (3.0, 3.0, 0.4), cam)
    extractor = FeatureExtractor(cam, FeatureConfig(threads=1, max_features=10_000))
    a = extractor.extract(image)
    b = extractor.extract(np.roll(image, 512, axis=1))
    assert len(a) > 50
    assert abs(len(a) - len(b)) <= 0.05 * len(a)
    # Every feature of the rolled image is a feature of the original turned by pi.
    shifted = np.array([angle_diff(x, math.pi) for x in b.bearing_rad])
    d = (
        np.abs(np.vectorize(angle_diff)(shifted[:, None], a.bearing_rad[None, :]))
        + np.abs(b.v[:, None] - a.v[None, :]) * cam.rad_per_px
    )
    close = d.min(axis=1) < 0.5 * cam.rad_per_px
    assert close.mean() > 0.9


def test_sift_option_float_descriptors_and_the_same_seam_handling() -> None:
    cam = PanoramaCamera(width=1024, height=256)
    image, _ = render_panorama(small_world(), (3.0, 3.0, 0.4), cam)
    extractor = FeatureExtractor(cam, FeatureConfig(detector="sift", threads=2))
    a = extractor.extract(image)
    b = extractor.extract(np.roll(image, 512, axis=1))
    assert not a.binary and a.descriptors.dtype == np.float32
    assert a.descriptors.shape == (len(a), 128) and len(a) > 30
    shifted = np.array([angle_diff(x, math.pi) for x in b.bearing_rad])
    d = (
        np.abs(np.vectorize(angle_diff)(shifted[:, None], a.bearing_rad[None, :]))
        + np.abs(b.v[:, None] - a.v[None, :]) * cam.rad_per_px
    )
    assert (d.min(axis=1) < 0.5 * cam.rad_per_px).mean() > 0.8
