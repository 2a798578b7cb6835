"""Places and localisation status over HTTP against a real `covslam serve`."""

from __future__ import annotations

import httpx

from tests.e2e.conftest import create_map, frame_dicts, post_all, sim_frames

SIM = sim_frames(110, seed=3)
R1 = frame_dicts(SIM[:70])
START = 70


def _r2(k: int) -> dict:
    """r2 drives on from where r1 stopped, without an initial pose."""
    f = frame_dicts([SIM[START + k]])[0]
    f.pop("initial_pose", None)
    f.update(robot="r2", seq=k)
    if k == 0:
        f.pop("odometry", None)
    return f


def _problem(r: httpx.Response, status: int) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    return r.json()


def test_places_and_localisation_over_http(client: httpx.Client) -> None:
    map_id = create_map(client, "places", config={"landmark_cap": 40})
    results = post_all(client, map_id, R1)
    assert {r["localisation"]["status"] for r in results} == {"tracking"}

    r2 = post_all(client, map_id, [_r2(0)])
    pose = client.get(f"/v1/maps/{map_id}/pose")
    assert pose.status_code == 200, pose.text
    assert pose.json()["robots"]["r2"]["localisation"]["status"] == "initialising"
    assert pose.json()["robots"]["r2"]["seq"] == 0
    r2 += post_all(client, map_id, [_r2(k) for k in range(1, 40)])
    statuses = [r["localisation"]["status"] for r in r2]
    assert statuses[0] == "initialising"
    assert "relocalised" in statuses, statuses
    first = statuses.index("relocalised")
    assert statuses[-1] == "tracking" and set(statuses[first + 1 :]) == {"tracking"}
    pose = client.get(f"/v1/maps/{map_id}/pose").json()["robots"]
    assert pose["r2"]["localisation"]["status"] == "tracking"
    # every acknowledged frame is in the trajectory, those before the anchor with a source
    rows = client.get(f"/v1/maps/{map_id}/trajectory", params={"robot": "r2"}).json()
    rows = rows["robots"]["r2"]
    assert [r["seq"] for r in rows] == list(range(40))
    assert {r.get("source") for r in rows[:first]} == {"odometry"}
    assert all("source" not in r for r in rows[first:])

    doc = client.get(f"/v1/maps/{map_id}/places")
    assert doc.status_code == 200
    places = doc.json()
    assert places["map_id"] == map_id and places["places"], "learnt automatically"
    assert {"source", "target", "heading", "distance", "count"} <= set(places["transitions"][0])
    n = len(places["places"])

    learnt = client.post(f"/v1/maps/{map_id}/places", json={"robot": "r1"})
    assert learnt.status_code == 201, learnt.text
    assert learnt.json()["place"]["id"] == n and learnt.json()["place"]["robot"] == "r1"
    assert len(client.get(f"/v1/maps/{map_id}/places").json()["places"]) == n + 1

    # bad input: problem+json, nothing learnt
    assert (
        "ghost"
        in _problem(client.post(f"/v1/maps/{map_id}/places", json={"robot": "ghost"}), 404)[
            "detail"
        ]
    )
    _problem(client.post(f"/v1/maps/{map_id}/places", json={"robot": 5}), 422)
    _problem(client.post(f"/v1/maps/{map_id}/places", json={"where": "here"}), 422)
    _problem(client.get("/v1/maps/nope/places"), 404)
    assert len(client.get(f"/v1/maps/{map_id}/places").json()["places"]) == n + 1
