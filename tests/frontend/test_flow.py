"""Optical flow: a robot's last features followed into its next panorama."""

from __future__ import annotations

import math

import numpy as np

from frontend.cameras import PanoramaCamera
from frontend.features import FeatureConfig, FeatureExtractor, Features
from frontend.flow import FlowSeed, carry_features
from graph.angles import wrap_angles
from service.datasets.render import render_panorama, visible_corners
from tests.frontend._synthetic import small_world

CAM = PanoramaCamera(width=1024, height=256)


def _seed(image: np.ndarray, feats: Features, theta: float) -> FlowSeed:
    return FlowSeed(image, feats.u, feats.v, feats.octave, feats.response, theta)


def _empty_like(feats: Features) -> Features:
    return feats.subset(np.zeros(0, dtype=np.int64))


def _corner_bearing_errors(feats: Features, pose: tuple[float, float, float]) -> np.ndarray:
    """|bearing error| (rad) of each feature within 2 px of a visible poster corner."""
    _ids, bearings, elevations = visible_corners(small_world(), pose, CAM)
    cu, cv = CAM.column_of_bearing(bearings), CAM.row_of_elevation(elevations)
    du = np.abs(np.mod(feats.u[:, None] - cu[None, :] + CAM.width / 2, CAM.width) - CAM.width / 2)
    d = np.hypot(du, feats.v[:, None] - cv[None, :])
    j = np.argmin(d, axis=1)
    near = d[np.arange(len(feats)), j] <= 2.0
    return np.abs(wrap_angles(feats.bearing_rad[near] - bearings[j[near]]))


def test_convention_a_turn_moves_followed_features_to_their_new_bearings() -> None:
    """The robot turns 12 deg left and moves 5 cm: every followed corner feature lands at
    the corner's bearing from the new pose (within the detector's own accuracy)."""
    extractor = FeatureExtractor(CAM, FeatureConfig(threads=1))
    before_pose, after_pose = (3.0, 3.0, 0.4), (3.05, 3.0, 0.4 + math.radians(12.0))
    before, _ = render_panorama(small_world(), before_pose, CAM)
    after, _ = render_panorama(small_world(), after_pose, CAM)
    feats = extractor.extract(before)
    carried = carry_features(
        _seed(before, feats, before_pose[2]),
        after,
        math.radians(12.0),
        _empty_like(feats),
        extractor,
    )
    assert len(carried) >= 0.6 * len(feats)
    errors = _corner_bearing_errors(carried, after_pose)
    assert len(errors) >= 20
    assert np.median(errors) < 0.5 * CAM.rad_per_px
    # The descriptors were computed at the new positions (the extractor's own kind).
    again = extractor.describe(after, carried.u, carried.v, carried.octave)
    assert np.array_equal(again, carried.descriptors)


def test_followed_features_cross_the_seam() -> None:
    """Half a turn in place moves every column by width / 2: points near the seam and
    points that cross it come out at their bearing turned by pi."""
    extractor = FeatureExtractor(CAM, FeatureConfig(threads=1))
    pose = (3.0, 3.0, 0.4)
    image, _ = render_panorama(small_world(), pose, CAM)
    feats = extractor.extract(image)
    near_seam = (feats.u < 40) | (feats.u > CAM.width - 40)
    turned = (pose[0], pose[1], pose[2] + math.radians(185.0))
    after, _ = render_panorama(small_world(), turned, CAM)
    carried = carry_features(
        _seed(image, feats, pose[2]), after, math.radians(185.0), _empty_like(feats), extractor
    )
    expected = wrap_angles(feats.bearing_rad - math.radians(185.0))
    # Match each carried feature to the seed feature it came from by the expected bearing.
    d = np.abs(wrap_angles(carried.bearing_rad[:, None] - expected[None, :]))
    d += np.abs(carried.v[:, None] - feats.v[None, :]) * CAM.rad_per_px
    source = np.argmin(d, axis=1)
    good = d[np.arange(len(carried)), source] < 0.5 * CAM.rad_per_px
    assert good.mean() > 0.9
    assert near_seam.sum() >= 2 and np.isin(np.flatnonzero(near_seam), source[good]).any()
    # Features that were near the middle are now near the seam, and wrapped correctly.
    assert ((carried.u < 40) | (carried.u > CAM.width - 40)).sum() >= 2


def test_a_followed_point_on_a_detection_is_not_a_second_feature() -> None:
    extractor = FeatureExtractor(CAM, FeatureConfig(threads=1))
    pose = (3.0, 3.0, 0.4)
    image, _ = render_panorama(small_world(), pose, CAM)
    feats = extractor.extract(image)
    # The same image again: every followed point lands on its own detection.
    carried = carry_features(_seed(image, feats, pose[2]), image, 0.0, feats, extractor)
    assert len(carried) == len(feats)
    assert np.array_equal(carried.u, feats.u)
    # Without the detections, every point is followed (in place) once.
    alone = carry_features(_seed(image, feats, pose[2]), image, 0.0, _empty_like(feats), extractor)
    assert len(alone) >= 0.9 * len(feats)
    d = np.hypot(alone.u[:, None] - feats.u[None, :], alone.v[:, None] - feats.v[None, :])
    assert np.all(d.min(axis=1) < 0.05)


def test_nothing_to_follow_from_another_camera_or_an_empty_seed() -> None:
    extractor = FeatureExtractor(CAM, FeatureConfig(threads=1))
    image, _ = render_panorama(small_world(), (3.0, 3.0, 0.4), CAM)
    feats = extractor.extract(image)
    empty = _seed(image, _empty_like(feats), 0.0)
    assert carry_features(empty, image, 0.0, feats, extractor) is feats
    other = _seed(np.zeros((128, 512), dtype=np.uint8), feats, 0.0)
    assert carry_features(other, image, 0.0, feats, extractor) is feats
