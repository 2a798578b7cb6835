"""A map's config over REST: every estimator parameter a client sets reaches the worker's
estimator, bad values are refused naming the field, configs stored before the estimator
groups existed still load, an outdoor-scale world maps by config alone."""

from __future__ import annotations

import json
from dataclasses import fields

import httpx

from graph.config import SlamConfig
from service.exchange import EXPORT_FORMAT, EXPORT_VERSION
from service.offline.datasets.outdoor_sim import CONFIGS, outdoor_run
from service.offline.evaluation import ate_rmse, dead_reckoning, map_figures
from service.pipeline.config import SLAM_FIELD_PATHS, slam_config, slam_config_dict
from tests.e2e.conftest import create_map, frame_dicts, post_all, sim_frames
from tests.service.test_mapconfig import LEGACY_STORED_CONFIG, non_default_config


def test_every_estimator_parameter_set_over_rest_reaches_the_workers_estimator(
    client: httpx.Client,
) -> None:
    body, values = non_default_config()
    map_id = create_map(client, "every-parameter", config=body, mode="localisation")
    summary = client.get(f"/v1/maps/{map_id}").json()
    # `estimator` is the SlamConfig the map's worker process built and runs with.
    assert summary["estimator"] == {**values, "allow_new_landmarks": False}
    assert set(summary["estimator"]) == {f.name for f in fields(SlamConfig)}
    defaults = json.loads(json.dumps(slam_config_dict(SlamConfig())))
    assert all(summary["estimator"][k] != defaults[k] for k in values)
    assert summary["config"]["triangulation"] == body["triangulation"]


def test_bad_estimator_values_are_422_naming_the_field(client: httpx.Client) -> None:
    for config, field in [
        ({"triangulation": {"max_depth_m": -1}}, "config.triangulation.max_depth_m"),
        ({"gating": {"gate_confirm_rad": "wide"}}, "config.gating.gate_confirm_rad"),
        ({"keyframes": {"max_linked_keyframes": 0}}, "config.keyframes.max_linked_keyframes"),
        ({"solver": {"relinearize_skip": 0}}, "config.solver.relinearize_skip"),
        ({"triangulation": {"max_range_m": 9}}, "config.triangulation.max_range_m"),
    ]:
        r = client.post("/v1/maps", json={"name": "bad", "config": config})
        assert r.status_code == 422, r.text
        assert r.headers["content-type"].startswith("application/problem+json")
        assert r.json()["field"] == field
    r = client.post(
        "/v1/maps",
        json={"name": "bad", "config": {"triangulation": {"min_depth_m": 50, "max_depth_m": 20}}},
    )
    assert r.status_code == 422 and "min_depth_m < max_depth_m" in r.json()["detail"]
    assert all(m["name"] != "bad" for m in client.get("/v1/maps").json())  # nothing created


def test_a_map_stored_before_the_estimator_groups_imports_with_the_defaults(
    client: httpx.Client,
) -> None:
    frames = frame_dicts(sim_frames(30))
    doc = {
        "format": EXPORT_FORMAT,
        "version": EXPORT_VERSION,
        "map": {"name": "legacy", "mode": "mapping", "config": LEGACY_STORED_CONFIG},
        "frames": [{"frame": f, "result": None} for f in frames],
    }
    r = client.post(
        "/v1/maps/import",
        content=json.dumps(doc).encode(),
        headers={"content-type": "application/json"},
    )
    assert r.status_code == 201, r.text
    map_id = r.json()["id"]
    summary = client.get(f"/v1/maps/{map_id}").json()
    expected = slam_config_dict(slam_config(LEGACY_STORED_CONFIG, "mapping"))
    assert summary["estimator"] == json.loads(json.dumps(expected))
    assert summary["estimator"]["max_depth_m"] == SlamConfig().max_depth_m
    assert summary["counts"]["frames"] == len(frames)
    more = [{**f, "seq": f["seq"] + len(frames), "stamp": f["stamp"] + 100.0} for f in frames[1:4]]
    assert len(post_all(client, map_id, more)) == 3


def test_an_outdoor_world_maps_by_config_alone(client: httpx.Client) -> None:
    """Trees 5-80 m from a 334 m loop: with the defaults (depth to 15 m, position sigma
    0.3 m) few become landmarks; with the outdoor triangulation set in the map's config
    most do, and the map is accurate where it stands (unaligned) and in shape."""
    run = outdoor_run(3, small=True)
    frames = frame_dicts(run.frames)
    figures = {}
    for name in ("default", "outdoor"):
        map_id = create_map(client, f"outdoor-{name}", config=CONFIGS[name])
        figures[name] = map_figures(client, map_id, run, post_all(client, map_id, frames))
    observed = figures["outdoor"]["trees_observed"]
    assert observed == len(run.landmarks)
    assert figures["default"]["trees_initialised"] <= 0.2 * observed
    outdoor = figures["outdoor"]
    assert outdoor["trees_initialised"] >= 0.85 * observed
    assert outdoor["landmarks_live"] == outdoor["landmark_initialisations"]  # uncapped
    assert outdoor["landmarks_live"] == outdoor["trees_initialised"]
    dead = dead_reckoning(run.frames)
    assert outdoor["ate_rmse_m"] < min(1.5, 0.25 * ate_rmse(dead, run.ground_truth))
    assert outdoor["ate_rmse_aligned_m"] < 1.0
    assert outdoor["landmark_rmse_m"] < 1.5
    assert outdoor["config"]["triangulation"]["max_depth_m"] == 100.0


def test_the_openapi_schema_documents_every_estimator_parameter(client: httpx.Client) -> None:
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    for name, path in SLAM_FIELD_PATHS.items():
        model = "MapConfig"
        for key in path[:-1]:
            model = schemas[model]["properties"][key]["$ref"].rsplit("/", 1)[-1]
        text = schemas[model]["properties"][name].get("description", "")
        assert text, (model, name)
        unit = {"_m": "metres", "_rad": "radians"}.get(name[name.rfind("_") :])
        assert unit is None or unit in text, (model, name, text)
