"""The archive over HTTP: GET landmarks?state=archived and the landmark_restored event."""

from __future__ import annotations

import httpx
import pytest

from tests.e2e.conftest import Server, create_map, frame_dicts, sim_frames
from tests.e2e.test_events_export import post_and_collect

FRAMES = frame_dicts(sim_frames(160, seed=3))


@pytest.mark.parametrize("upkeep", ["in_frame", "after_frame"])
def test_archived_landmarks_and_restore_events(
    server: Server, client: httpx.Client, upkeep: str
) -> None:
    """Also with the budget in the worker's upkeep, once each frame's result is sent."""
    config = {"landmark_cap": 4, "solver": {"upkeep": upkeep}}
    map_id = create_map(client, f"archive-{upkeep}", config=config)
    _, events = post_and_collect(server, client, map_id, FRAMES)

    live = client.get(f"/v1/maps/{map_id}/landmarks")
    default = client.get(f"/v1/maps/{map_id}/landmarks?state=live")
    assert live.status_code == default.status_code == 200 and live.json() == default.json()
    assert all(set(lm) == set(live.json()[0]) for lm in live.json())
    assert "cluster" in live.json()[0] and "removals" not in live.json()[0]
    archived = client.get(f"/v1/maps/{map_id}/landmarks", params={"state": "archived"}).json()
    assert archived, "a cap of 4 removes landmarks"
    for entry in archived:
        assert {"id", "label", "x", "y", "covariance", "observed_from", "removals"} <= set(entry)
        assert entry["removals"] >= 1 and entry["observed_from"]["n"] >= 1
    live_ids = {lm["id"] for lm in live.json()}
    assert live_ids.isdisjoint(a["id"] for a in archived)
    # a label is one landmark for the map's life
    labels = [lm["label"] for lm in live.json()] + [a["label"] for a in archived]
    assert len(labels) == len(set(labels))

    restored = [e["data"] for e in events if e["event"] == "landmark_restored"]
    removed = [e["data"] for e in events if e["event"] == "landmark_marginalised"]
    assert restored, "a landmark seen again after its removal comes back"
    for doc in restored:
        assert {"id", "label", "x", "y", "restorations", "frame_id"} <= set(doc)
        assert any(r["landmark_id"] == doc["id"] and r["label"] == doc["label"] for r in removed)
    added = [e["data"]["id"] for e in events if e["event"] == "landmark_added"]
    assert len(added) == len(set(added)), "an id is handed out once"
    # every removal is in the log (the stream was read up to the last frame's result;
    # that frame's removals follow it)
    assert client.get(f"/v1/maps/{map_id}").json()["counts"]["removals"] >= len(removed)

    bad = client.get(f"/v1/maps/{map_id}/landmarks", params={"state": "ghost"})
    assert bad.status_code == 422
    assert bad.headers["content-type"].startswith("application/problem+json")
