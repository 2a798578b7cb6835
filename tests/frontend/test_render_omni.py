"""The renderer's ground truth, and omni ring <-> panorama equivalence on one scene."""

from __future__ import annotations

import math

import numpy as np

from frontend.cameras import OmniCamera, PanoramaCamera
from frontend.features import FeatureConfig, FeatureExtractor
from graph.angles import wrap_angles
from service.offline.datasets.render import raycast, render_omni, render_panorama, visible_corners
from tests.frontend._synthetic import small_world

POSE = (4.1, 2.7, 0.9)


def test_convention_rendered_corners_come_out_at_their_true_bearing() -> None:
    """A poster corner at a known bearing (ground truth) is detected at that bearing."""
    tw = small_world()
    cam = PanoramaCamera(2048, 512)
    image, truth = render_panorama(tw, POSE, cam)
    ids, bearings, elevations = visible_corners(tw, POSE, cam)
    assert len(ids) > 40
    feats = FeatureExtractor(cam, FeatureConfig(threads=1)).extract(image)
    cu, cv = cam.column_of_bearing(bearings), cam.row_of_elevation(elevations)
    du = np.mod(feats.u[:, None] - cu[None, :] + 1024, 2048) - 1024
    d = np.hypot(du, feats.v[:, None] - cv[None, :])
    j = d.argmin(axis=1)
    near = d[np.arange(len(j)), j] < 2.0
    assert near.sum() > 30
    err = np.abs(wrap_angles(feats.bearing_rad[near] - bearings[j[near]]))
    assert np.median(err) < math.radians(0.2)
    # Per-column truth: the wall point each column sees lies at the column's bearing.
    col = 700
    x, y, th = POSE
    wx, wy = truth.wall_xy[col]
    seen = math.atan2(wy - y, wx - x) - th
    assert abs(float(wrap_angles(seen - cam.bearing_of_column(col)))) < 1e-9
    assert truth.face[col] >= 0 and math.isfinite(truth.distance_m[col])


def test_raycast_hits_the_nearest_wall() -> None:
    tw = small_world()
    # From the centre of room 0 (6 m rooms), looking along -x: the wall x = 0 at 3 m.
    hit = raycast(tw, (3.0, 3.0, math.pi), np.array([0.0, math.pi / 2]))
    assert abs(hit.distance_m[0] - 3.0) < 1e-9
    assert abs(hit.distance_m[1] - 3.0) < 1e-9  # +pi/2 from facing -x is -y: wall y = 0


def test_omni_ring_unwraps_to_the_panorama_of_the_same_scene() -> None:
    tw = small_world()
    omni = OmniCamera(
        width=640,
        height=640,
        centre_xy=(320.0, 320.0),
        inner_radius_px=60.0,
        outer_radius_px=310.0,
        forward_rad=math.radians(30.0),
        mirrored=True,
        pano_width=1024,
        pano_height=256,
    )
    pano_cam = omni.panorama
    pano, _ = render_panorama(tw, POSE, pano_cam)
    ring = render_omni(tw, POSE, omni)
    unwrapped = omni.unwrap(ring)
    diff = np.abs(unwrapped.astype(np.int16) - pano.astype(np.int16))
    assert np.median(diff) <= 2 and diff.mean() < 8
    extractor = FeatureExtractor(pano_cam, FeatureConfig(threads=1))
    a = extractor.extract(pano)
    b = extractor.extract(unwrapped)
    assert len(a) > 50 and len(b) > 50
    d = np.abs(wrap_angles(a.bearing_rad[:, None] - b.bearing_rad[None, :]))
    d = d + np.abs(a.v[:, None] - b.v[None, :]) * pano_cam.rad_per_px
    best = d.min(axis=1)
    close = best < 2 * pano_cam.rad_per_px
    assert close.mean() > 0.6
    assert np.median(best[close]) < 0.5 * pano_cam.rad_per_px
