"""A map's config: every estimator parameter reachable and validated, stored configs
that still load, the camera map's default bound on landmark factors per frame, the pose
window's defaults."""

from __future__ import annotations

import json
from dataclasses import fields, replace
from pathlib import Path
from typing import Any, cast, get_args

import pytest
from pydantic import ValidationError
from pydantic.fields import FieldInfo

from graph.config import SlamConfig
from graph.policies import POLICY_NAMES
from service.pipeline.camera_config import (
    CAMERA_GRAPH_FRAME_DISTANCE_M,
    CAMERA_LANDMARK_CAP,
    CAMERA_LANDMARK_FACTORS,
    CAMERA_NOISE_DEFAULTS,
)
from service.pipeline.config import SLAM_FIELD_PATHS, MapConfig, slam_config, slam_config_dict


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


def test_window_growth_defaults_and_a_window_given_alone() -> None:
    defaults = SlamConfig()
    omitted = slam_config(MapConfig.model_validate({}).model_dump(mode="json"), "mapping")
    assert (omitted.pose_window, omitted.window_observations, omitted.max_pose_window) == (
        defaults.pose_window,
        defaults.window_observations,
        defaults.max_pose_window,
    )
    # pose_window alone (as every map stored before the growth existed): exactly that window.
    alone = MapConfig.model_validate({"pose_window": 30})
    assert (alone.pose_window, alone.window_observations) == (30, None)
    stored = alone.model_dump(mode="json")
    assert slam_config(stored, "mapping").window_observations is None
    both = MapConfig.model_validate({"pose_window": 30, "window_observations": 200})
    assert slam_config(both.model_dump(mode="json"), "mapping").window_observations == 200
    # A window given longer than the growth's limit is still that long.
    long = slam_config(MapConfig.model_validate({"pose_window": 900}).model_dump(), "mapping")
    assert (long.pose_window, long.window_observations) == (900, None)


def test_an_uncapped_maps_window_grows_unless_its_config_says_otherwise() -> None:
    """A new uncapped map grows its window by uncapped_window_observations; a config
    giving window_observations (as every map stored before that default did, null
    included) or pose_window alone keeps what it says; a new capped map grows by
    window_observations, one stored before that default keeps its window."""
    new = MapConfig.model_validate({"landmark_cap": None})
    assert slam_config(new.model_dump(mode="json"), "mapping").window_factor_bound == 900
    legacy = {**new.model_dump(mode="json"), "window_observations": None}
    del legacy["uncapped_window_observations"]
    assert slam_config(legacy, "mapping").window_factor_bound is None
    explicit = MapConfig.model_validate({"landmark_cap": None, "window_observations": 300})
    assert slam_config(explicit.model_dump(mode="json"), "mapping").window_factor_bound == 300
    alone = MapConfig.model_validate({"landmark_cap": None, "pose_window": 40})
    assert slam_config(alone.model_dump(mode="json"), "mapping").window_factor_bound is None
    capped = MapConfig.model_validate({"landmark_cap": 8})
    assert slam_config(capped.model_dump(mode="json"), "mapping").window_factor_bound == 900
    stored = {**capped.model_dump(mode="json"), "window_observations": None}
    assert slam_config(stored, "mapping").window_factor_bound is None


def test_removal_margin_reaches_the_estimator_and_must_stay_below_the_cap() -> None:
    assert slam_config({"landmark_cap": 50, "removal_margin": 5}, "mapping").removal_margin == 5
    assert slam_config({}, "mapping").removal_margin == 0
    with pytest.raises(ValueError, match="removal_margin"):
        slam_config({"landmark_cap": 5, "removal_margin": 5}, "mapping")


def test_a_new_map_bounds_its_window_by_marginals_and_a_stored_one_keeps_its_own() -> None:
    """At creation a map without window_marginals gets the estimator's bound; an explicit
    value (null included) is kept, and a stored config (or an export) without the field
    replays with no such bound, as it was processed."""
    default = SlamConfig().window_marginals
    assert default is not None
    new = MapConfig.model_validate({}).for_new_map(50)
    assert new.window_marginals == default
    stored = new.model_dump(mode="json")
    assert slam_config(stored, "mapping").window_marginals == default
    camera = MapConfig.model_validate({"camera": "panorama"}).for_new_map(50)
    assert camera.window_marginals == default
    free = MapConfig.model_validate({"window_marginals": None}).for_new_map(50)
    assert free.window_marginals is None
    assert MapConfig.model_validate({"window_marginals": 7}).for_new_map(50).window_marginals == 7
    old = {k: v for k, v in stored.items() if k != "window_marginals"}
    assert slam_config(old, "mapping").window_marginals is None
    with pytest.raises(ValidationError):
        MapConfig.model_validate({"window_marginals": 0})


def test_keyframe_placement_reaches_the_estimator_and_defaults_to_spacing() -> None:
    assert slam_config({}, "mapping").keyframe_placement == "spacing"
    given = {"keyframes": {"keyframe_placement": "area"}}
    stored = MapConfig.model_validate(given).for_new_map(50).model_dump(mode="json")
    assert slam_config(stored, "mapping").keyframe_placement == "area"
    with pytest.raises(ValidationError):
        MapConfig.model_validate({"keyframes": {"keyframe_placement": "time"}})


def test_a_camera_map_is_created_with_graph_frames_and_a_stored_one_keeps_its_own() -> None:
    """At creation a camera map without graph_frame_distance_m gets the camera's; a map
    without a camera, an explicit value (null included) and a stored config (or an export)
    without the field keep theirs, so a map built with every frame replays that way."""
    new = MapConfig.model_validate({"camera": "panorama"}).for_new_map(50)
    assert new.graph_frame_distance_m == CAMERA_GRAPH_FRAME_DISTANCE_M
    assert new.landmark_cap == CAMERA_LANDMARK_CAP
    stored = new.model_dump(mode="json")
    assert stored["graph_frame_distance_m"] == CAMERA_GRAPH_FRAME_DISTANCE_M
    assert slam_config(stored, "mapping").graph_frame_distance_m == CAMERA_GRAPH_FRAME_DISTANCE_M
    assert MapConfig.model_validate({}).for_new_map(50).graph_frame_distance_m is None
    every = MapConfig.model_validate({"camera": "panorama", "graph_frame_distance_m": None})
    assert every.for_new_map(50).graph_frame_distance_m is None
    given = MapConfig.model_validate({"camera": "panorama", "graph_frame_distance_m": 0.5})
    assert given.for_new_map(50).graph_frame_distance_m == 0.5
    old = {k: v for k, v in stored.items() if k != "graph_frame_distance_m"}
    assert slam_config(old, "mapping").graph_frame_distance_m is None


def test_a_camera_map_is_created_with_the_camera_loss_and_a_stored_one_keeps_huber() -> None:
    """A camera map created without a bearing loss or scale gets Geman-McClure; a map
    without a camera, a client's own loss or huber_k, and a stored config without the
    field (every map stored before it existed) keep Huber's."""
    new = MapConfig.model_validate({"camera": "panorama"}).for_new_map(50)
    stored = new.model_dump(mode="json")
    cfg = slam_config(stored, "mapping")
    assert (cfg.bearing_loss, cfg.huber_k) == (
        CAMERA_NOISE_DEFAULTS["bearing_loss"],
        CAMERA_NOISE_DEFAULTS["huber_k"],
    )
    assert cfg.bearing_loss == "geman_mcclure"
    plain = slam_config(MapConfig.model_validate({}).for_new_map(50).model_dump(), "mapping")
    assert (plain.bearing_loss, plain.huber_k) == ("huber", SlamConfig().huber_k)
    own_k = MapConfig.model_validate({"camera": "panorama", "noise": {"huber_k": 2.0}})
    assert own_k.for_new_map(50).noise.bearing_loss == "huber"
    assert own_k.for_new_map(50).noise.huber_k == 2.0
    own_loss = MapConfig.model_validate({"camera": "panorama", "noise": {"bearing_loss": "huber"}})
    assert own_loss.for_new_map(50).noise.huber_k == SlamConfig().huber_k
    old = dict(stored, noise={k: v for k, v in stored["noise"].items() if k != "bearing_loss"})
    assert slam_config(old, "mapping").bearing_loss == "huber"
    with pytest.raises(ValidationError):
        MapConfig.model_validate({"noise": {"bearing_loss": "tukey"}})
    with pytest.raises(ValueError, match="bearing_loss"):
        SlamConfig(bearing_loss="tukey")  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("field", "bad"),
    [
        ("graph_frame_distance_m", 0),
        ("graph_frame_distance_m", -0.1),
        ("graph_frame_distance_m", "far"),
        ("graph_frame_angle_rad", 0),
        ("graph_frame_max_gap", 0),
        ("graph_frame_min_landmarks", -1),
    ],
)
def test_graph_frame_settings_are_validated(field: str, bad: object) -> None:
    with pytest.raises(ValidationError, match=field):
        MapConfig.model_validate({"camera": "panorama", field: bad})


def test_graph_frame_settings_reach_the_estimator() -> None:
    given = {"graph_frame_angle_rad": 0.7, "graph_frame_max_gap": 9, "graph_frame_min_landmarks": 3}
    stored = MapConfig.model_validate({"camera": "panorama", **given}).for_new_map(None)
    estimator = slam_config(stored.model_dump(mode="json"), "mapping")
    assert {k: getattr(estimator, k) for k in given} == given


def test_a_camera_map_gets_the_camera_default_cap_unless_it_gives_one() -> None:
    """A camera map created without a cap gets the camera's default (the service's
    `default_camera_landmark_cap`), a map without a camera the plain default; a client's
    own cap, null (uncapped) included, is kept."""
    camera = MapConfig.model_validate({"camera": "panorama"})
    assert camera.for_new_map(50).landmark_cap == CAMERA_LANDMARK_CAP
    assert camera.for_new_map(50, 120).landmark_cap == 120
    assert camera.for_new_map(50, None).landmark_cap is None
    assert MapConfig.model_validate({}).for_new_map(50, 120).landmark_cap == 50
    own = MapConfig.model_validate({"camera": "panorama", "landmark_cap": 30})
    assert own.for_new_map(50, 120).landmark_cap == 30
    uncapped = MapConfig.model_validate({"camera": "panorama", "landmark_cap": None})
    assert uncapped.for_new_map(50, 120).landmark_cap is None


def test_a_new_map_gets_the_odometry_random_walks_and_a_stored_one_keeps_none() -> None:
    created = MapConfig.model_validate({}).for_new_map(50)
    estimator = slam_config(created.model_dump(mode="json"), "mapping")
    defaults = SlamConfig()
    assert estimator.odometry_sigma_per_sqrt_metre == defaults.odometry_sigma_per_sqrt_metre
    assert estimator.odometry_sigma_per_sqrt_radian == defaults.odometry_sigma_per_sqrt_radian
    assert defaults.odometry_sigma_per_sqrt_radian > 0
    # A config stored before the random walks existed replays without them.
    stored = MapConfig.model_validate({}).model_dump(mode="json")
    for field in ("odometry_sigma_per_sqrt_metre", "odometry_sigma_per_sqrt_radian"):
        del stored["noise"][field]
    old = slam_config(stored, "mapping")
    assert old.odometry_sigma_per_sqrt_metre == (0.0, 0.0, 0.0)
    assert old.odometry_sigma_per_sqrt_radian == 0.0
    # What a client states is kept, at creation as after.
    given = MapConfig.model_validate({"noise": {"odometry_sigma_per_sqrt_radian": 0.01}})
    kept = slam_config(given.for_new_map(50).model_dump(mode="json"), "mapping")
    assert kept.odometry_sigma_per_sqrt_radian == 0.01
    assert kept.odometry_sigma_per_sqrt_metre == defaults.odometry_sigma_per_sqrt_metre


@pytest.mark.parametrize(
    "noise",
    [
        {"odometry_sigma_per_sqrt_radian": -0.1},
        {"odometry_sigma_per_sqrt_metre": [0.1, -0.1, 0.0]},
        {"odometry_sigma_per_sqrt_metre": [0.1, 0.1]},
    ],
)
def test_odometry_random_walks_are_validated(noise: dict[str, object]) -> None:
    with pytest.raises(ValidationError, match="odometry_sigma_per_sqrt"):
        MapConfig.model_validate({"noise": noise})


# --------------------------------------------------------------------------- every parameter

MODE_ONLY = {"allow_new_landmarks"}
"""SlamConfig fields set by the map's mode, not its config."""

LEGACY_STORED_CONFIG: dict[str, Any] = {
    "landmark_cap": 50,
    "policy": "coverage",
    "pose_window": 100,
    "window_observations": None,
    "uncapped_window_observations": 900,
    "max_pose_window": 600,
    "camera": None,
    "noise": {
        "bearing_sigma_rad": 0.017453292519943295,
        "huber_k": 1.345,
        "bearing_loss": "huber",
        "odometry_sigma_floor": [0.002, 0.002, 0.003490658503988659],
        "odometry_sigma_per_metre": [0.03, 0.03, 0.017453292519943295],
        "odometry_sigma_per_radian": 0.02,
        "odometry_sigma_per_sqrt_second": [0.0, 0.0, 0.0],
        "initial_pose_sigma": [0.01, 0.01, 0.008726646259971648],
    },
    "optimizer": "dogleg",
    "max_landmark_factors": None,
    "removal_margin": 0,
    "drop_window_observations": False,
    "graph_frame_distance_m": None,
    "graph_frame_angle_rad": 0.7853981633974483,
    "graph_frame_max_gap": 8,
    "graph_frame_min_landmarks": 5,
    "seed": 0,
}
"""A map's config as the service stored it before triangulation, gating, keyframes and
solver were in it (a map created with `{}` under the default cap 50)."""


def _leaf(path: tuple[str, ...]) -> FieldInfo:
    model: Any = MapConfig
    for key in path[:-1]:
        model = model.model_fields[key].annotation
    return cast(FieldInfo, model.model_fields[path[-1]])


def _other_value(name: str) -> Any:
    """A valid value of a SlamConfig field other than its default, as JSON."""
    default = getattr(SlamConfig(), name)
    annotation = _leaf(SLAM_FIELD_PATHS[name]).annotation
    if name == "policy":
        return next(p for p in POLICY_NAMES if p != default)
    if isinstance(default, bool):
        return not default
    if default is None:
        kind = next(a for a in get_args(annotation) if a is not type(None))
        return 7 if kind is int else 0.7
    if isinstance(default, int):
        return default + 1
    if isinstance(default, float):
        return default * 1.5 if default else 0.5
    if isinstance(default, tuple):
        return [v * 1.5 + 0.001 for v in default]
    if isinstance(default, str):
        return next(a for a in get_args(annotation) if a != default)
    raise AssertionError(f"no other value for {name}={default!r}")


def _at(path: tuple[str, ...], value: Any) -> dict[str, Any]:
    body: dict[str, Any] = {path[-1]: value}
    for key in reversed(path[:-1]):
        body = {key: body}
    return body


def non_default_config() -> tuple[dict[str, Any], dict[str, Any]]:
    """A map config (REST body) giving every estimator parameter a value other than its
    default, and those values by SlamConfig field name (as JSON)."""
    values = {name: _other_value(name) for name in SLAM_FIELD_PATHS}
    body: dict[str, Any] = {}
    for name, value in values.items():
        path = SLAM_FIELD_PATHS[name]
        group = body
        for key in path[:-1]:
            group = group.setdefault(key, {})
        group[path[-1]] = value
    return body, values


@pytest.mark.parametrize("name", [f.name for f in fields(SlamConfig)])
def test_every_estimator_parameter_has_a_place_in_the_map_config(name: str) -> None:
    """A SlamConfig field without a map-config route (or the mode) fails here."""
    if name in MODE_ONLY:
        assert name not in SLAM_FIELD_PATHS
        assert slam_config({}, "mapping").allow_new_landmarks
        assert not slam_config({}, "localisation").allow_new_landmarks
        return
    assert name in SLAM_FIELD_PATHS, f"SlamConfig.{name} cannot be set through a map config"
    path = SLAM_FIELD_PATHS[name]
    assert path[-1] == name
    value = _other_value(name)
    stored = MapConfig.model_validate(_at(path, value)).model_dump(mode="json")
    got = getattr(slam_config(stored, "mapping"), name)
    assert json.loads(json.dumps(got)) == value
    assert got != getattr(SlamConfig(), name)
    description = _leaf(path).description or ""
    assert len(description) > 20, f"{name}: describe it (with its unit) for the OpenAPI schema"
    if name.endswith("_m"):
        assert "metres" in description, name
    if name.endswith("_rad"):
        assert "radians" in description, name


def test_every_estimator_parameter_at_once_and_the_defaults_are_the_estimators() -> None:
    body, values = non_default_config()
    estimator = slam_config(MapConfig.model_validate(body).model_dump(mode="json"), "mapping")
    assert json.loads(json.dumps(slam_config_dict(estimator))) == {
        **values,
        "allow_new_landmarks": True,
    }
    created = MapConfig.model_validate({"landmark_cap": 50}).for_new_map(50)
    assert slam_config(created.model_dump(mode="json"), "mapping") == SlamConfig()


def test_a_config_stored_before_the_groups_loads_with_the_estimators_defaults() -> None:
    loaded = slam_config(LEGACY_STORED_CONFIG, "mapping")
    # As it was built: no odometry random walks, a capped window that does not grow (and
    # no bound by marginals), the optimizer it stored (dogleg, the default then) and
    # everything in the frame.
    assert loaded == replace(
        SlamConfig(),
        window_observations=None,
        window_marginals=None,
        optimizer="dogleg",
        odometry_sigma_per_sqrt_metre=(0.0, 0.0, 0.0),
        odometry_sigma_per_sqrt_radian=0.0,
        upkeep="in_frame",
        relinearise_budget=None,
    )
    assert MapConfig.model_validate(LEGACY_STORED_CONFIG).triangulation.max_depth_m == 15.0
    # A stored config dumped now holds every group, and reloads to the same estimator.
    created = MapConfig.model_validate({"triangulation": {"max_depth_m": 100.0}}).for_new_map(50)
    stored = json.loads(json.dumps(created.model_dump(mode="json")))
    assert {"triangulation", "gating", "keyframes", "solver"} <= set(stored)
    assert slam_config(stored, "mapping") == replace(SlamConfig(), max_depth_m=100.0)


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"triangulation": {"max_depth_m": -1}}, "max_depth_m"),
        ({"triangulation": {"max_depth_m": "far"}}, "max_depth_m"),
        ({"triangulation": {"min_rays": 1}}, "min_rays"),
        ({"triangulation": {"min_parallax_rad": 0}}, "min_parallax_rad"),
        ({"triangulation": {"max_position_sigma_m": 0}}, "max_position_sigma_m"),
        ({"triangulation": {"landmark_prior_sigma_m": 0}}, "landmark_prior_sigma_m"),
        ({"triangulation": {"min_depth_m": 20, "max_depth_m": 10}}, "max_depth_m"),
        ({"triangulation": {"min_rays": 5, "max_rays": 4}}, "max_rays"),
        ({"triangulation": {"depth": 1}}, "depth"),
        ({"gating": {"max_innovation_rad": 4.0}}, "max_innovation_rad"),
        ({"gating": {"gate_min_age_frames": -1}}, "gate_min_age_frames"),
        ({"keyframes": {"max_keyframes": -1}}, "max_keyframes"),
        ({"keyframes": {"keyframe_angle_rad": 0}}, "keyframe_angle_rad"),
        ({"solver": {"relinearize_skip": 0}}, "relinearize_skip"),
        ({"solver": {"relinearize_threshold": -0.1}}, "relinearize_threshold"),
    ],
)
def test_bad_estimator_values_are_refused_naming_the_field(
    body: dict[str, Any], field: str
) -> None:
    with pytest.raises(ValidationError, match=field):
        MapConfig.model_validate(body)


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"min_parallax_rad": 0.0}, "min_parallax_rad"),
        ({"max_position_sigma_m": 0.0}, "max_position_sigma_m"),
        ({"landmark_prior_sigma_m": 0.0}, "landmark_prior_sigma_m"),
        ({"max_innovation_rad": -1.0}, "max_innovation_rad"),
        ({"relinearize_skip": 0}, "relinearize_skip"),
        ({"keyframe_distance_m": -1.0}, "keyframe_distance_m"),
        ({"odometry_sigma_floor": (0.0, -1.0, 0.0)}, "sigmas"),
        ({"min_depth_m": 2.0, "max_depth_m": 1.0}, "min_depth_m"),
    ],
)
def test_the_estimator_refuses_what_the_map_config_refuses(
    change: dict[str, Any], match: str
) -> None:
    with pytest.raises(ValueError, match=match):
        replace(SlamConfig(), **change)


def test_the_configuration_guide_lists_every_estimator_parameter() -> None:
    guide = (Path(__file__).resolve().parents[2] / "docs" / "configuration.md").read_text()
    missing = [".".join(p) for p in SLAM_FIELD_PATHS.values() if f"`{'.'.join(p)}`" not in guide]
    assert not missing, f"docs/configuration.md lacks {missing}"
