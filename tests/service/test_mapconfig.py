"""A map's config: the camera map's default bound on landmark factors per frame."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from service.mapconfig import CAMERA_LANDMARK_FACTORS, MapConfig, slam_config


def test_camera_map_defaults_to_the_landmark_factor_bound() -> None:
    config = MapConfig.model_validate({"camera": "panorama"})
    assert config.max_landmark_factors == CAMERA_LANDMARK_FACTORS
    assert slam_config(config.model_dump(mode="json"), "mapping").max_landmark_factors == (
        CAMERA_LANDMARK_FACTORS
    )


def test_map_without_camera_has_no_bound_and_explicit_values_are_kept() -> None:
    assert MapConfig.model_validate({}).max_landmark_factors is None
    unbounded = MapConfig.model_validate({"camera": "panorama", "max_landmark_factors": None})
    assert unbounded.max_landmark_factors is None
    # The stored config (model_dump) says null explicitly: reloading keeps it unbounded.
    stored = unbounded.model_dump(mode="json")
    assert slam_config(stored, "mapping").max_landmark_factors is None
    assert MapConfig.model_validate({"max_landmark_factors": 12}).max_landmark_factors == 12


def test_max_landmark_factors_must_be_positive() -> None:
    with pytest.raises(ValidationError, match="max_landmark_factors"):
        MapConfig.model_validate({"camera": "panorama", "max_landmark_factors": 0})


def test_drop_window_observations_reaches_the_estimator() -> None:
    stored = MapConfig.model_validate({"drop_window_observations": True}).model_dump(mode="json")
    assert slam_config(stored, "mapping").drop_window_observations is True
    assert slam_config({}, "mapping").drop_window_observations is False
