"""A camera robot without initial_pose over HTTP against a real `covslam serve`: it is
accepted as `initialising`, listed by GET /pose, relocalised from its images within a
few frames near the truth, then tracked; its trajectory keeps every frame."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import pytest

from graph.localiser import INITIALISING, RELOCALISED, TRACKING
from service.offline.datasets.camera_runs import (
    CONFIG,
    Leg,
    mapping_path,
    pose_error,
    render_leg,
    scene,
    start_pose,
    straight,
)
from tests.e2e.conftest import Server, create_map

SEED = 11


@pytest.fixture(scope="module")
def legs() -> tuple[Leg, Leg]:
    world = scene(SEED)
    mapping = render_leg(
        world, mapping_path(), robot="r1", rng=np.random.default_rng([SEED, 1]), initial_pose=True
    )
    start = start_pose(mapping.truth, np.random.default_rng([SEED, 2]), 0.4)
    newcomer = render_leg(world, straight(start, 10), robot="r2", rng=np.random.default_rng(SEED))
    return mapping, newcomer


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[httpx.Client]:
    srv = Server(tmp_path_factory.mktemp("svc-camloc") / "data", workers=1)
    srv.start()
    try:
        with httpx.Client(base_url=srv.url, timeout=120) as c:
            yield c
    finally:
        srv.stop()


def _post(client: httpx.Client, map_id: str, meta: dict[str, Any], image: bytes) -> dict:
    r = client.post(
        f"/v1/maps/{map_id}/frames",
        data={"meta": json.dumps(meta)},
        files={"image": ("frame.png", image, "image/png")},
    )
    assert r.status_code == 200, r.text
    return dict(r.json())


def test_a_camera_robot_starts_without_initial_pose_over_http(
    client: httpx.Client, legs: tuple[Leg, Leg]
) -> None:
    mapping, newcomer = legs
    map_id = create_map(client, "camloc", config=CONFIG)
    for meta, image in mapping.frames:
        assert _post(client, map_id, meta, image)["localisation"]["status"] == TRACKING

    results = []
    for k, (meta, image) in enumerate(newcomer.frames):
        assert "initial_pose" not in meta
        results.append(_post(client, map_id, meta, image))
        if k == 0:
            assert results[0]["localisation"]["status"] == INITIALISING
            pose = client.get(f"/v1/maps/{map_id}/pose").json()["robots"]["r2"]
            assert pose["localisation"]["status"] == INITIALISING
            assert pose["seq"] == 0
    statuses = [r["localisation"]["status"] for r in results]
    k = statuses.index(RELOCALISED)
    assert k < 6, statuses
    assert set(statuses[:k]) == {INITIALISING} and set(statuses[k + 1 :]) == {TRACKING}
    for r, truth in zip(results[k:], newcomer.truth[k:], strict=True):
        e_m, e_deg = pose_error(r["pose"], truth)
        assert e_m < 0.3 and e_deg < 10.0, (r["seq"], e_m, e_deg)
    assert results[-1]["timing_ms"]["localise_cpu"] > 0
    pose = client.get(f"/v1/maps/{map_id}/pose").json()["robots"]["r2"]
    assert pose["localisation"]["status"] == TRACKING
    rows = client.get(f"/v1/maps/{map_id}/trajectory", params={"robot": "r2"}).json()
    rows = rows["robots"]["r2"]
    assert [row["seq"] for row in rows] == list(range(len(newcomer.frames)))
    assert {row.get("source") for row in rows[:k]} == {"odometry"}
