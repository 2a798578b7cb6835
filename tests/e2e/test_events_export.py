"""Live events (SSE with resumable ids) and the export -> import round trip."""

from __future__ import annotations

import json
import threading
import time

import httpx
import numpy as np

from tests.e2e.conftest import Server, create_map, frame_dicts, post_all, sim_frames

FRAMES = frame_dicts(sim_frames(120, seed=3))


def _collect(
    url: str, path: str, headers: dict[str, str], want: int, out: list[dict], ready: threading.Event
) -> None:
    """Read SSE events until `want` frame events arrived (or 60 s passed)."""
    deadline = time.monotonic() + 60
    with (
        httpx.Client(base_url=url, timeout=httpx.Timeout(60, read=20)) as c,
        c.stream("GET", path, headers=headers) as r,
    ):
        assert r.status_code == 200
        assert r.headers["content-type"].startswith("text/event-stream")
        event: dict = {}
        for line in r.iter_lines():
            ready.set()
            if line.startswith("id: "):
                event["id"] = int(line[4:])
            elif line.startswith("event: "):
                event["event"] = line[7:]
            elif line.startswith("data: "):
                event["data"] = json.loads(line[6:])
            elif line == "" and event:
                out.append(event)
                event = {}
                if sum(e["event"] == "frame" for e in out) >= want:
                    return
            if time.monotonic() > deadline:
                return


def post_and_collect(
    server: Server, client: httpx.Client, map_id: str, frames: list[dict]
) -> tuple[list[dict], list[dict]]:
    """Post `frames` while reading the map's event stream: (frame results, events up to
    the last frame's result)."""
    path = f"/v1/maps/{map_id}/events"
    events: list[dict] = []
    ready = threading.Event()
    reader = threading.Thread(
        target=_collect, args=(server.url, path, {}, len(frames), events, ready)
    )
    reader.start()
    assert ready.wait(10)
    results = post_all(client, map_id, frames)
    reader.join(timeout=60)
    return results, events


def test_events_stream_frame_results_and_resume_after_last_event_id(
    server: Server, client: httpx.Client
) -> None:
    map_id = create_map(client, "live", config={"landmark_cap": 6})
    path = f"/v1/maps/{map_id}/events"
    results, events = post_and_collect(server, client, map_id, FRAMES)
    frames = [e for e in events if e["event"] == "frame"]
    assert [e["data"] for e in frames] == results
    ids = [e["id"] for e in events]
    assert ids == sorted(ids) and len(set(ids)) == len(ids)
    kinds = {e["event"] for e in events}
    assert {"frame", "landmark_added", "landmark_marginalised"} <= kinds
    added = [e["data"]["id"] for e in events if e["event"] == "landmark_added"]
    assert added == [i for r in results for i in r["landmarks"]["added"]]

    # A client that saw up to the 50th frame event reconnects with Last-Event-ID.
    cut = frames[49]["id"]
    resumed: list[dict] = []
    again = threading.Event()
    _collect(server.url, path, {"Last-Event-ID": str(cut)}, len(FRAMES) - 50, resumed, again)
    assert [e["id"] for e in resumed] == [i for i in ids if i > cut]


def test_export_import_round_trip(client: httpx.Client) -> None:
    map_id = create_map(client, "exported", config={"landmark_cap": 8, "seed": 4})
    post_all(client, map_id, FRAMES)
    doc = client.get(f"/v1/maps/{map_id}/export").json()
    assert doc["format"] == "covslam.map" and doc["version"] == 1
    assert {"map", "estimator", "landmarks", "trajectories", "removals", "frames"} <= set(doc)
    assert len(doc["frames"]) == len(FRAMES) and doc["removals"]
    assert all("covariance" in lm and "observed_from" in lm for lm in doc["landmarks"])

    r = client.post("/v1/maps/import", json=doc)
    assert r.status_code == 201, r.text
    new_id = r.json()["id"]
    assert new_id != map_id and r.json()["counts"]["frames"] == len(FRAMES)
    copy = client.get(f"/v1/maps/{new_id}/export").json()
    for a, b in zip(doc["frames"], copy["frames"], strict=True):
        assert a["frame"] == b["frame"]
        assert a["result"]["pose"] == b["result"]["pose"]
    assert [lm["id"] for lm in copy["landmarks"]] == [lm["id"] for lm in doc["landmarks"]]
    np.testing.assert_allclose(
        [[lm["x"], lm["y"]] for lm in copy["landmarks"]],
        [[lm["x"], lm["y"]] for lm in doc["landmarks"]],
        atol=1e-9,
    )
    assert copy["removals"] == doc["removals"]
    # the copy is a working map: retries are idempotent there too
    again = client.post(f"/v1/maps/{new_id}/frames", json=FRAMES[-1])
    assert again.headers.get("idempotent-replayed") == "true"


def test_import_refuses_bad_documents(client: httpx.Client) -> None:
    before = len(client.get("/v1/maps").json())
    for doc, needle in (
        ({"format": "other"}, "format"),
        ({"format": "covslam.map", "version": 99}, "version"),
        (
            {
                "format": "covslam.map",
                "version": 1,
                "map": {"name": "x", "mode": "mapping", "config": {}},
                "frames": [{"frame": {"robot": "r1"}}],
            },
            "frames[0].frame",
        ),
    ):
        r = client.post("/v1/maps/import", json=doc)
        assert r.status_code == 422, r.text
        assert needle in r.json()["detail"]
    assert len(client.get("/v1/maps").json()) == before
