"""ImageFrontEnd: an image frame through front end and estimator; bad images change nothing."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from frontend.association import AssociationConfig
from frontend.cameras import PanoramaCamera
from frontend.errors import ImageError
from frontend.pipeline import FrontEnd
from graph.config import SlamConfig
from graph.slam import BearingSlam
from graph.types import FrameInput, Odometry, Pose2D
from service.offline.datasets.indoor_sim import make_world
from service.offline.datasets.render import make_textured_world, render_panorama
from service.pipeline.images import ImageFrontEnd
from service.pipeline.robots import RobotState

CAM = PanoramaCamera(1024, 256)


def _pipeline() -> ImageFrontEnd:
    return ImageFrontEnd(
        BearingSlam(SlamConfig(landmark_cap=None), rng=np.random.default_rng(0)), FrontEnd(CAM)
    )


def test_prediction_composes_odometry_and_grows_the_covariance() -> None:
    p = _pipeline()
    first = FrameInput("r1", 0, 0.0, initial_pose=Pose2D(1.0, 2.0, math.pi / 2))
    pose, cov = p.predict(first)
    assert np.allclose(pose, (1.0, 2.0, math.pi / 2))
    p.robots["r1"] = RobotState(pose=(pose, cov))
    nxt = FrameInput("r1", 1, 0.1, odometry=Odometry(0.5, 0.0, 0.1))
    pose2, cov2 = p.predict(nxt)
    # Forward is +y in the map when theta = pi/2.
    assert np.allclose(pose2, (1.0, 2.5, math.pi / 2 + 0.1))
    assert np.all(np.linalg.eigvalsh(cov2 - cov) > 0)


def test_bad_image_leaves_map_and_front_end_unchanged() -> None:
    rng = np.random.default_rng(2)
    tw = make_textured_world(make_world(rooms=(2, 1), landmarks=2, rng=rng), rng=rng)
    p = _pipeline()
    image, _ = render_panorama(tw, (3.0, 3.0, 0.0), CAM)
    first = FrameInput("r1", 0, 0.0, initial_pose=Pose2D(3.0, 3.0, 0.0))
    result = p.submit(first, image)
    assert result.outcome.frame_index == 0
    tracks = p.front_end.associator.track_count("r1")
    assert tracks > 20
    nxt = FrameInput("r1", 1, 0.1, odometry=Odometry(0.1, 0.0, 0.0))
    for bad in (b"", b"not an image", np.zeros((10, 10), dtype=np.uint8)):
        with pytest.raises(ImageError):
            p.submit(nxt, bad)
    assert p.slam.frame_count == 1
    assert p.front_end.associator.track_count("r1") == tracks
    image2, _ = render_panorama(tw, (3.1, 3.0, 0.0), CAM)
    second = p.submit(nxt, image2)
    # The second sighting reports tracks to the estimator as candidates.
    assert second.association.kind.count("track") > 10
    p.front_end.close()


def test_a_restored_snapshot_takes_the_services_association_settings() -> None:
    """A snapshot pickled before the last two AssociationConfig fields existed (unpickling
    gives a config without them) is restored with the running service's settings, which
    a map's config does not carry."""
    current = AssociationConfig()
    old_values = [getattr(current, f.name) for f in dataclasses.fields(AssociationConfig)]
    old_config = object.__new__(AssociationConfig)
    old_config.__setstate__(old_values[:-2])  # what unpickling an older snapshot gives
    with pytest.raises(AttributeError):
        _ = old_config.coincident_rad
    source = _pipeline()
    source.front_end.associator.config = old_config
    restored = _pipeline()
    restored.set_associator(source.front_end.associator)
    assert restored.front_end.associator.config == current
