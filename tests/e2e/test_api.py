"""REST API v1 against a real `covslam serve`: endpoints, bad input, idempotency, modes."""

from __future__ import annotations

import itertools
import json
import math
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import pytest

from service.pipeline.camera_config import CAMERA_LANDMARK_CAP
from tests.e2e.conftest import Server, create_map, frame_dicts, post_all, sim_frames

FRAMES = frame_dicts(sim_frames(160))


@pytest.fixture(scope="module")
def mapped(client: httpx.Client) -> tuple[str, list[dict]]:
    """A map that received FRAMES (cap 8, so the budget marginalises)."""
    map_id = create_map(client, "mapped", config={"landmark_cap": 8})
    return map_id, post_all(client, map_id, FRAMES)


def _problem(r: httpx.Response, status: int) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    body = r.json()
    assert body["status"] == status and body["type"].startswith("urn:covslam:problem:")
    assert body["title"] and body["detail"]
    return body


def _frames_in(client: httpx.Client, map_id: str) -> int:
    return int(client.get(f"/v1/maps/{map_id}").json()["counts"]["frames"])


def test_map_lifecycle(client: httpx.Client) -> None:
    r = client.post("/v1/maps", json={"name": "life", "config": {"landmark_cap": 5}})
    assert r.status_code == 201
    body = r.json()
    assert r.headers["location"] == f"/v1/maps/{body['id']}"
    assert body["config"]["landmark_cap"] == 5 and body["mode"] == "mapping"
    assert body["estimator"]["allow_new_landmarks"] is True
    assert body["id"] in [m["id"] for m in client.get("/v1/maps").json()]
    r = client.patch(f"/v1/maps/{body['id']}", json={"mode": "localisation"})
    assert r.status_code == 200 and r.json()["estimator"]["allow_new_landmarks"] is False
    assert client.delete(f"/v1/maps/{body['id']}").status_code == 204
    _problem(client.get(f"/v1/maps/{body['id']}"), 404)
    assert body["id"] not in [m["id"] for m in client.get("/v1/maps").json()]


def test_default_cap_comes_from_settings_and_null_means_uncapped(client: httpx.Client) -> None:
    default = client.post("/v1/maps", json={"name": "d"}).json()
    assert default["estimator"]["landmark_cap"] == 50
    camera = client.post("/v1/maps", json={"name": "c", "config": {"camera": "panorama"}})
    assert camera.status_code == 201, camera.text
    assert camera.json()["estimator"]["landmark_cap"] == CAMERA_LANDMARK_CAP
    uncapped = client.post("/v1/maps", json={"name": "u", "config": {"landmark_cap": None}})
    assert uncapped.json()["estimator"]["landmark_cap"] is None
    assert default["estimator"]["optimizer"] == "gauss_newton"
    damped = client.post("/v1/maps", json={"name": "g", "config": {"optimizer": "dogleg"}})
    assert damped.json()["estimator"]["optimizer"] == "dogleg"


def test_frames_give_results_and_the_map_answers(
    client: httpx.Client, mapped: tuple[str, list[dict]]
) -> None:
    map_id, results = mapped
    assert [r["seq"] for r in results] == [f["seq"] for f in FRAMES]
    assert [r["frame_id"] for r in results] == list(range(1, len(FRAMES) + 1))
    last = results[-1]
    assert set(last) >= {"frame_id", "robot", "seq", "pose", "covariance", "localisation"}
    assert np.asarray(last["covariance"]).shape == (3, 3)
    # A frame's answer comes before the upkeep's removals (the map's default upkeep),
    # which the next frame's answer lists: each upkeep brings the map back to the cap.
    for frame, following in itertools.pairwise(results):
        assert frame["landmarks"]["live"] - len(following["landmarks"]["marginalised"]) <= 8
    assert max(r["landmarks"]["live"] for r in results) > 8, "the run must pass the cap"
    assert sum(len(r["landmarks"]["marginalised"]) for r in results) > 0

    summary = client.get(f"/v1/maps/{map_id}").json()
    assert summary["counts"]["frames"] == len(FRAMES)
    assert summary["timing_ms"]["p50"] > 0

    pose = client.get(f"/v1/maps/{map_id}/pose").json()["robots"]["r1"]
    assert pose["seq"] == FRAMES[-1]["seq"]
    assert np.asarray(pose["covariance"]).shape == (3, 3)

    traj = client.get(f"/v1/maps/{map_id}/trajectory").json()["robots"]["r1"]
    assert [p["seq"] for p in traj] == [f["seq"] for f in FRAMES]
    assert math.isclose(traj[-1]["x"], pose["pose"]["x"], abs_tol=1e-9)

    landmarks = client.get(f"/v1/maps/{map_id}/landmarks").json()
    assert 0 < len(landmarks) <= 8
    for lm in landmarks:
        cov = np.asarray(lm["covariance"])
        assert cov.shape == (2, 2)
        assert math.isclose(lm["information"], 1 / cov[0, 0] + 1 / cov[1, 1], rel_tol=1e-9)
        assert lm["observed_from"]["n"] > 0

    coverage = client.get(f"/v1/maps/{map_id}/coverage", params={"cell_m": 0.5}).json()
    members = sorted(i for c in coverage["clusters"] for i in c["members"])
    assert members == sorted(lm["id"] for lm in landmarks)
    assert len(coverage["clusters"]) == math.ceil(len(landmarks) / 4)
    assert all(c["spread"] >= 0 for c in coverage["clusters"])
    grid = coverage["grid"]
    assert grid["explored_cells"] > 0 and len(grid["counts"]) == grid["height"]
    for hole in grid["holes"]:
        assert grid["counts"][hole["iy"]][hole["ix"]] == 0
    assert coverage["removal_count"] == len(coverage["removals"]) > 0
    assert all(r["reason"] and r["policy"] == "coverage" for r in coverage["removals"])


def test_trajectory_as_tum(client: httpx.Client, mapped: tuple[str, list[dict]]) -> None:
    map_id, _ = mapped
    r = client.get(f"/v1/maps/{map_id}/trajectory", params={"robot": "r1", "format": "tum"})
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    rows = np.loadtxt(r.text.splitlines(), comments="#")
    traj = client.get(f"/v1/maps/{map_id}/trajectory").json()["robots"]["r1"]
    assert rows.shape == (len(FRAMES), 8)
    np.testing.assert_allclose(rows[:, 1], [p["x"] for p in traj], atol=1e-6)
    yaw = 2 * np.arctan2(rows[:, 6], rows[:, 7])
    np.testing.assert_allclose(
        np.angle(np.exp(1j * (yaw - [p["theta"] for p in traj]))), 0, atol=1e-5
    )
    _problem(client.get(f"/v1/maps/{map_id}/trajectory", params={"format": "tum"}), 422)
    _problem(client.get(f"/v1/maps/{map_id}/trajectory", params={"robot": "nobody"}), 404)


def test_idempotent_retry_and_out_of_order(
    client: httpx.Client, mapped: tuple[str, list[dict]]
) -> None:
    map_id, results = mapped
    before = _frames_in(client, map_id)
    again = client.post(f"/v1/maps/{map_id}/frames", json=FRAMES[10])
    assert again.status_code == 200 and again.headers["idempotent-replayed"] == "true"
    assert again.json() == results[10]
    changed = {**FRAMES[10], "stamp": FRAMES[10]["stamp"] + 0.01}
    assert _problem(client.post(f"/v1/maps/{map_id}/frames", json=changed), 409)["field"] == "seq"
    stale = {**FRAMES[-1], "seq": FRAMES[-1]["seq"] - 1, "stamp": FRAMES[-1]["stamp"] + 1}
    stale_seq = {**stale, "seq": FRAMES[-1]["seq"] + 1000, "stamp": 0.0}
    _problem(client.post(f"/v1/maps/{map_id}/frames", json=stale), 409)
    assert _problem(client.post(f"/v1/maps/{map_id}/frames", json=stale_seq), 409)["field"] == (
        "stamp"
    )
    assert _frames_in(client, map_id) == before


@pytest.mark.parametrize(
    ("body", "status", "needle"),
    [
        (b'{"robot": "r1", "seq": ', 400, "malformed JSON"),
        (b'{"robot": "r1", "seq": 999, "stamp": NaN}', 400, "NaN"),
        (b'{"robot": "r1", "seq": 999, "stamp": Infinity}', 400, "Infinity"),
        (b'{"robot": "r1", "seq": 999, "stamp": 1e999}', 400, "infinity"),
        (b"[1, 2]", 400, "JSON object"),
        (b"", 400, "empty"),
        (b'{"robot": 7, "seq": 999, "stamp": 1}', 422, "robot: must be a string"),
        (b'{"robot": "r1", "seq": "9", "stamp": 1}', 422, "seq: must be an integer"),
        (b'{"robot": "r1", "seq": 1.5, "stamp": 1}', 422, "non-integer"),
        (b'{"robot": "r1", "stamp": 1}', 422, "seq: is required"),
        (
            b'{"robot": "r1", "seq": 999, "stamp": 1e9, "odometry": {"dx": 0, "dy": 0, '
            b'"dtheta": 0}, "observations": [{"bearing": 4.0, "label": "3"}]}',
            422,
            "observations[0].bearing",
        ),
        (
            b'{"robot": "r1", "seq": 999, "stamp": 1e9, "odometry": {"dx": true, "dy": 0, '
            b'"dtheta": 0}}',
            422,
            "odometry.dx",
        ),
        (
            b'{"robot": "new", "seq": 0, "stamp": 1, "initial_pose": {"x": 0, "y": "a", '
            b'"theta": 0}}',
            422,
            "initial_pose.y",
        ),
        (b'{"robot": "r1", "seq": 999, "stamp": 1e9}', 422, "odometry: is required"),
        (b'{"robot": "r1", "seq": 1' + b"0" * 5000 + b', "stamp": 1}', 400, "too many digits"),
        # An unknown field (here a typo of "observations") is refused, not ignored.
        (
            b'{"robot": "r1", "seq": 999, "stamp": 1e9, "odometry": {"dx": 0, "dy": 0, '
            b'"dtheta": 0}, "observation": [{"bearing": 0.1, "label": "3"}]}',
            422,
            "observation: is not a field of a frame",
        ),
        # Bounds (settings `frames`): a name, a label, a stamp, odometry, a first pose.
        (b'{"robot": "' + b"r" * 129 + b'", "seq": 0, "stamp": 1}', 422, "robot: must be at most"),
        (
            b'{"robot": "r1", "seq": 999, "stamp": 1e9, "odometry": {"dx": 0, "dy": 0, '
            b'"dtheta": 0}, "observations": [{"bearing": 0.1, "label": "' + b"x" * 65 + b'"}]}',
            422,
            "observations[0].label: must be at most 64 characters",
        ),
        (b'{"robot": "r1", "seq": 999, "stamp": 1e308}', 422, "stamp: must lie within"),
        (
            b'{"robot": "r1", "seq": 999, "stamp": 1e9, "odometry": {"dx": 1e5, "dy": 0, '
            b'"dtheta": 0}}',
            422,
            "odometry.dx: must lie within +-100 m",
        ),
        (
            b'{"robot": "new", "seq": 0, "stamp": 1, "initial_pose": {"x": 0, "y": -3e6, '
            b'"theta": 0}}',
            422,
            "initial_pose.y: must lie within",
        ),
        (b'{"robot": "r1", "seq": 9223372036854775808, "stamp": 1e9}', 422, "seq: must be < 2^63"),
        (b'{"robot": "r\\ud800", "seq": 0, "stamp": 1}', 422, "robot: must be Unicode text"),
    ],
)
def test_bad_frames_are_refused_and_leave_the_map_unchanged(
    client: httpx.Client, mapped: tuple[str, list[dict]], body: bytes, status: int, needle: str
) -> None:
    map_id, _ = mapped
    before = client.get(f"/v1/maps/{map_id}/pose").json()
    r = client.post(
        f"/v1/maps/{map_id}/frames", content=body, headers={"content-type": "application/json"}
    )
    problem = _problem(r, status)
    assert needle in problem["detail"], problem
    if status == 422:
        assert problem["detail"].startswith(f"{problem['field']}: "), problem
    assert client.get(f"/v1/maps/{map_id}/pose").json() == before


def test_too_many_observations_are_refused(
    client: httpx.Client, mapped: tuple[str, list[dict]]
) -> None:
    map_id, _ = mapped
    before = _frames_in(client, map_id)
    frame = {**FRAMES[-1], "seq": 10**6, "stamp": 1e9}
    frame["observations"] = [{"bearing": 0.0, "label": str(i)} for i in range(1001)]
    problem = _problem(client.post(f"/v1/maps/{map_id}/frames", json=frame), 422)
    assert problem["field"] == "observations"
    assert problem["detail"] == "observations: must hold at most 1000, got 1001"
    assert _frames_in(client, map_id) == before


def test_oversized_body_is_413(client: httpx.Client, mapped: tuple[str, list[dict]]) -> None:
    map_id, _ = mapped
    huge = {**FRAMES[-1], "seq": 10**6, "padding": "x" * (2 << 20)}
    problem = _problem(client.post(f"/v1/maps/{map_id}/frames", json=huge), 413)
    assert "exceeds the limit" in problem["detail"]


def test_unknown_map_and_bad_config(client: httpx.Client) -> None:
    assert "nope" in _problem(client.post("/v1/maps/nope/frames", json=FRAMES[0]), 404)["detail"]
    for path in ("", "/pose", "/trajectory", "/landmarks", "/coverage", "/export", "/places"):
        _problem(client.get(f"/v1/maps/nope{path}"), 404)
    bad = client.post("/v1/maps", json={"name": "x", "config": {"landmark_cap": 0}})
    assert _problem(bad, 422)["field"] == "config.landmark_cap"
    bad = client.post("/v1/maps", json={"name": "x", "config": {"policy": "magic"}})
    assert "unknown policy" in _problem(bad, 422)["detail"]
    bad = client.post("/v1/maps", json={"name": "x", "config": {"optimizer": "lm"}})
    assert _problem(bad, 422)["field"] == "config.optimizer"
    bad = client.post("/v1/maps", json={"name": "x", "config": {"sigma": 1}})
    assert "config.sigma" in _problem(bad, 422)["detail"]
    _problem(client.post("/v1/maps", json={"name": "x", "mode": "dreaming"}), 422)
    raw = client.post("/v1/maps", content=b"{", headers={"content-type": "application/json"})
    _problem(raw, 400)


def test_image_frames_need_a_camera_and_places_are_documented(
    client: httpx.Client, mapped: tuple[str, list[dict]]
) -> None:
    map_id, _ = mapped
    r = client.post(
        f"/v1/maps/{map_id}/frames",
        files={"image": ("p.png", b"\x89PNG", "image/png")},
        data={"meta": json.dumps({"robot": "r1", "seq": 10**6, "stamp": 1e9})},
    )
    assert _problem(r, 422)["type"].endswith(":no-camera")  # tests/e2e/test_images.py
    schema = client.get("/openapi.json").json()
    frames_body = schema["paths"]["/v1/maps/{map_id}/frames"]["post"]["requestBody"]["content"]
    assert {"application/json", "multipart/form-data"} <= set(frames_body)
    assert "/v1/maps/{map_id}/places" in schema["paths"]
    assert client.get("/docs").status_code == 200
    refs = set()

    def walk(node: object) -> None:
        if isinstance(node, dict):
            refs.update(v for k, v in node.items() if k == "$ref")
            for v in node.values():
                walk(v)
        elif isinstance(node, list):
            for v in node:
                walk(v)

    walk(schema)
    names = set(schema["components"]["schemas"])
    assert "#/components/schemas/FrameIn" in refs
    assert {r.rsplit("/", 1)[-1] for r in refs} <= names, "every $ref resolves"


def test_openapi_fields_carry_units_and_conventions(client: httpx.Client) -> None:
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    bearing = schemas["ObservationIn"]["properties"]["bearing"]["description"]
    assert "radians" in bearing and "counter-clockwise" in bearing and "robot frame" in bearing
    units = ("metres", "radians", "m²", "seconds", "milliseconds", "1/m²")
    quantities = {
        "PoseXYTheta": ("x", "y", "theta"),
        "OdometryIn": ("dx", "dy", "dtheta", "sigma_x", "sigma_y", "sigma_theta"),
        "TrajectoryPoint": ("stamp", "x", "y", "theta"),
        "LandmarkOut": ("x", "y", "covariance", "information", "first_stamp", "last_stamp"),
        "ObservedFrom": ("x", "y"),
        "FrameResult": ("stamp", "covariance", "timing_ms"),
        "RobotPose": ("stamp", "covariance"),
        "FrameIn": ("stamp",),
        "Cluster": ("spread", "centre"),
        "CoverageGrid": ("cell_m", "radius_m", "origin"),
        "Hole": ("x", "y"),
    }
    for name, props in quantities.items():
        for prop in props:
            text = schemas[name]["properties"][prop].get("description", "")
            assert any(u in text for u in units), (name, prop, text)
    for name in quantities:
        for prop, spec in schemas[name]["properties"].items():
            assert spec.get("description") or "$ref" in str(spec), (name, prop)


def test_localisation_mode_adds_no_landmarks(client: httpx.Client) -> None:
    map_id = create_map(client, "frozen", mode="localisation")
    results = post_all(client, map_id, FRAMES[:80])
    assert all(not r["landmarks"]["added"] for r in results)
    assert client.get(f"/v1/maps/{map_id}/landmarks").json() == []


def test_two_robots_share_one_map_concurrently(client: httpx.Client) -> None:
    r1 = frame_dicts(sim_frames(100, seed=5, robot="r1"))
    r2 = frame_dicts(sim_frames(100, seed=5, robot="r2"))  # same world, same labels
    map_id = create_map(client, "multi", config={"landmark_cap": None})
    with ThreadPoolExecutor(2) as pool:
        a, b = pool.map(
            lambda frames: post_all(httpx.Client(base_url=str(client.base_url)), map_id, frames),
            (r1, r2),
        )
    assert len(a) == len(b) == 100
    traj = client.get(f"/v1/maps/{map_id}/trajectory").json()["robots"]
    assert set(traj) == {"r1", "r2"} and len(traj["r1"]) == len(traj["r2"]) == 100
    labels = [lm["label"] for lm in client.get(f"/v1/maps/{map_id}/landmarks").json()]
    assert len(labels) == len(set(labels)) > 0, "one landmark per label, shared by both robots"
    observed = [{i for r in run for i in r["landmarks"]["observed"]} for run in (a, b)]
    added = [{i for r in run for i in r["landmarks"]["added"]} for run in (a, b)]
    # Which robot initialises a shared landmark depends on which frame the map took first.
    shared = (observed[1] & added[0]) | (observed[0] & added[1])
    assert shared, "a robot observes landmarks the other initialised"


def test_two_maps_in_parallel_match_a_lone_run(
    client: httpx.Client, mapped: tuple[str, list[dict]]
) -> None:
    _, lone = mapped
    ids = [create_map(client, f"par{i}", config={"landmark_cap": 8}) for i in range(2)]
    with ThreadPoolExecutor(2) as pool:
        runs = list(
            pool.map(
                lambda m: post_all(httpx.Client(base_url=str(client.base_url)), m, FRAMES), ids
            )
        )
    workers = {client.get(f"/v1/maps/{m}").json()["worker"] for m in ids}
    for run in runs:
        assert [r["pose"] for r in run] == [r["pose"] for r in lone]
        assert [r["landmarks"]["marginalised"] for r in run] == [
            r["landmarks"]["marginalised"] for r in lone
        ]
    assert workers <= {0, 1}


def test_metrics_and_probes(client: httpx.Client, mapped: tuple[str, list[dict]]) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200 and ready.json()["workers"] == 2
    assert "pid" not in ready.text  # open to anyone: counts only
    assert len(client.get("/v1/workers").json()["workers"]) == 2
    text = client.get("/metrics").text
    for name in (
        "covslam_frames_total",
        "covslam_frame_stage_milliseconds_bucket",
        "covslam_live_landmarks",
        "covslam_marginalisations_total",
        "covslam_worker_restarts_total",
    ):
        assert name in text, name
    map_id, _ = mapped
    line = next(
        ln for ln in text.splitlines() if ln.startswith(f'covslam_frames_total{{map="{map_id}"}}')
    )
    assert float(line.split()[-1]) == len(FRAMES)


def test_frame_limits_come_from_settings(tmp_path: Path) -> None:
    """COVSLAM_FRAMES__* bound what one frame may hold; a frame beyond one is a 422."""
    server = Server(tmp_path / "data", workers=1, env={"COVSLAM_FRAMES__MAX_LABEL_CHARS": "3"})
    server.start()
    try:
        with httpx.Client(base_url=server.url, timeout=60) as client:
            map_id = create_map(client, "limits")
            frame = {
                "robot": "r",
                "seq": 0,
                "stamp": 0.0,
                "initial_pose": {"x": 0, "y": 0, "theta": 0},
            }
            long = {**frame, "observations": [{"bearing": 0.1, "label": "abcd"}]}
            problem = _problem(client.post(f"/v1/maps/{map_id}/frames", json=long), 422)
            assert problem["detail"] == "observations[0].label: must be at most 3 characters, got 4"
            assert _frames_in(client, map_id) == 0
            short = {**frame, "observations": [{"bearing": 0.1, "label": "abc"}]}
            assert client.post(f"/v1/maps/{map_id}/frames", json=short).status_code == 200
    finally:
        server.stop()
