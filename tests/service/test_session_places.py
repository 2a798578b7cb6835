"""MapSession with the place localiser: a robot without initial pose, places, restart."""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np
import pytest

from graph.angles import wrap_angle
from service import queries
from service.errors import ServiceError
from service.frames_io import frame_to_dict
from service.session import MapSession
from service.settings import StoreSettings
from service.store import MapRecord
from tests.graph._world import circle_frames

FRAMES, TRUTH, _ = circle_frames(120, seed=4)
START = 60  # r2 drives the same circle, starting where r1 was at frame 60


def _new(path: Path) -> MapSession:
    record = MapRecord("m1", "test", "mapping", {"landmark_cap": 40}, time.time())
    return MapSession.create(path, record, StoreSettings(snapshot_every=1000))


def _r2(k: int) -> dict:
    """r2's k-th frame: r1's frame START + k, without initial pose."""
    f = dataclasses.replace(FRAMES[START + k], robot="r2", seq=k, initial_pose=None)
    if k == 0:
        f = dataclasses.replace(f, odometry=None)
    return frame_to_dict(f)


@pytest.fixture(scope="module")
def mapped(tmp_path_factory: pytest.TempPathFactory) -> tuple[MapSession, list[dict], Path]:
    path = tmp_path_factory.mktemp("places") / "m1.sqlite"
    session = _new(path)
    for f in FRAMES[:START]:
        result = json.loads(session.submit(frame_to_dict(f)).result_json)
        assert result["localisation"]["status"] == "tracking"
    r2 = [json.loads(session.submit(_r2(k)).result_json) for k in range(30)]
    return session, r2, path


def test_robot_without_initial_pose_is_found_and_anchored(mapped) -> None:
    session, r2, _ = mapped
    statuses = [r["localisation"]["status"] for r in r2]
    assert statuses[0] == "initialising"
    first = statuses.index("relocalised")
    assert first <= 20
    assert set(statuses[:first]) == {"initialising"}
    assert set(statuses[first + 1 :]) == {"tracking"}
    for r in r2[:first]:
        assert r["landmarks"]["observed"] == []  # the graph did not take these frames
    for k in range(first, 30):
        truth = TRUTH[START + k]
        pose = r2[k]["pose"]
        assert math.hypot(pose["x"] - truth[0], pose["y"] - truth[1]) < 0.3
        assert abs(wrap_angle(pose["theta"] - truth[2])) < math.radians(5)
    assert "r2" in session.slam.robots
    poses = queries.Pose().answer(session)["robots"]
    assert poses["r2"]["localisation"]["status"] == "tracking"


def test_places_learnt_listed_and_learn_now(mapped) -> None:
    session, _, _ = mapped
    doc = queries.Places().answer(session)
    assert doc["places"], "places are learnt automatically while tracking"
    for place in doc["places"]:
        assert len(place["landmarks"]) >= 2
        assert all(lm["depth"] > 0 and lm["depth_variance"] >= 0 for lm in place["landmarks"])
    before = len(doc["places"])
    learnt = queries.LearnPlace("r1").answer(session)
    assert learnt["place"]["id"] == before and len(learnt["places"]) == before + 1
    p = learnt["place"]["pose"]
    assert math.hypot(p["x"] - TRUTH[START - 1][0], p["y"] - TRUTH[START - 1][1]) < 0.3
    with pytest.raises(ServiceError) as err:
        queries.LearnPlace("nobody").answer(session)
    assert err.value.status == 404
    assert len(queries.Places().answer(session)["places"]) == before + 1


def test_localiser_state_survives_a_restart(mapped) -> None:
    session, _, path = mapped
    places = queries.Places().answer(session)
    session.snapshot()
    session.submit(_r2(30))  # one frame in the log's tail after the snapshot
    expected = queries.Pose().answer(session)["robots"]["r2"]
    session.close()
    reopened = MapSession(path, StoreSettings(snapshot_every=1000))
    assert queries.Places().answer(reopened)["places"] == places["places"] or len(
        queries.Places().answer(reopened)["places"]
    ) >= len(places["places"])
    got = queries.Pose().answer(reopened)["robots"]["r2"]
    assert got["localisation"]["status"] == expected["localisation"]["status"] == "tracking"
    np.testing.assert_allclose(
        [got["pose"]["x"], got["pose"]["y"]],
        [expected["pose"]["x"], expected["pose"]["y"]],
        atol=5e-3,
    )
    nxt = json.loads(reopened.submit(_r2(31)).result_json)
    assert nxt["localisation"]["status"] == "tracking"
    reopened.close()


def test_first_frame_without_pose_and_bad_input_leave_the_map_unchanged(tmp_path: Path) -> None:
    session = _new(tmp_path / "m2.sqlite")
    result = json.loads(session.submit(_r2(0)).result_json)
    assert result["localisation"]["status"] == "initialising"
    assert session.slam.robots == []
    bad = _r2(1)
    bad["odometry"] = None  # required after a robot's first frame, even initialising
    with pytest.raises(ServiceError) as err:
        session.submit(bad)
    assert err.value.status == 422
    with pytest.raises(ServiceError):
        session.submit(_r2(0) | {"seq": 0, "stamp": 99.0})  # a different frame, same seq
    assert session.store.frame_count() == 1
    with pytest.raises(ServiceError) as err:
        queries.LearnPlace("r2").answer(session)  # initialising: no pose to learn at
    assert err.value.status == 409
    session.close()
