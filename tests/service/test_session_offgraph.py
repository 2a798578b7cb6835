"""Frames the graph did not take (robot lost or initialising) are in the trajectory and
the pose endpoint: nothing acknowledged is ever lost."""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np
import pytest

from api.routes.queries import tum_text
from graph.angles import wrap_angle
from service import queries
from service.frames_io import frame_to_dict
from service.session import MapSession
from service.settings import StoreSettings
from service.store import MapRecord
from tests.graph._world import circle_frames

FRAMES, TRUTH, _ = circle_frames(260, seed=4)
CUT = (100, 140)
"""r1's frames CUT[0]..CUT[1]-1 are cut out: it jumps ~6 m along the circle, unseen."""
KEPT = [*range(CUT[0]), *range(CUT[1], len(FRAMES))]


def _new(path: Path) -> MapSession:
    record = MapRecord("m1", "test", "mapping", {"landmark_cap": 40}, time.time())
    return MapSession.create(path, record, StoreSettings(snapshot_every=1000))


@pytest.fixture(scope="module")
def kidnapped(tmp_path_factory: pytest.TempPathFactory) -> dict:
    session = _new(tmp_path_factory.mktemp("offgraph") / "m1.sqlite")
    statuses, while_lost = [], None
    for seq, k in enumerate(KEPT):
        frame = frame_to_dict(dataclasses.replace(FRAMES[k], seq=seq))
        result = json.loads(session.submit(frame).result_json)
        statuses.append(result["localisation"]["status"])
        if while_lost is None and statuses[-3:] == ["lost"] * 3:
            while_lost = {
                "seq": seq,
                "result": result,
                "trajectory": queries.Trajectory("r1").answer(session)["r1"],
                "pose": queries.Pose().answer(session)["robots"]["r1"],
            }
    yield {"session": session, "statuses": statuses, "while_lost": while_lost}
    session.close()


def test_frames_acknowledged_while_lost_are_in_the_trajectory(kidnapped) -> None:
    statuses = kidnapped["statuses"]
    lost = statuses.index("lost")
    assert CUT[0] <= lost <= CUT[0] + 20, "the jump is noticed"
    again = statuses.index("relocalised", lost)
    assert set(statuses[again + 1 :]) == {"tracking"}
    off_graph = range(lost + 1, again)
    assert len(off_graph) > 0

    # While lost: every frame so far is there, the gap's frames with a source.
    snap = kidnapped["while_lost"]
    assert [r["seq"] for r in snap["trajectory"]] == list(range(snap["seq"] + 1))
    gap = [r for r in snap["trajectory"] if r["seq"] > lost]
    assert gap and {r["source"] for r in gap} <= {"odometry", "filter"}
    last = snap["trajectory"][-1]
    assert last["x"] == snap["result"]["pose"]["x"] and last["y"] == snap["result"]["pose"]["y"]
    assert snap["pose"]["localisation"]["status"] == "lost"
    assert snap["pose"]["seq"] == snap["seq"]
    assert snap["pose"]["pose"]["x"] == last["x"]

    # Re-anchored: still every frame, in order; the gap dead-reckoned back from the anchor.
    rows = queries.Trajectory().answer(kidnapped["session"])["r1"]
    assert [r["seq"] for r in rows] == list(range(len(KEPT)))
    assert {r.get("source") for r in rows[lost + 1 : again]} == {"odometry"}
    assert all("source" not in r for r in (*rows[: lost + 1], *rows[again:]))
    truth = TRUTH[KEPT]
    xy = np.array([[r["x"], r["y"]] for r in rows])
    err = np.hypot(*(xy - truth[:, :2]).T)
    assert float(np.max(err[lost + 1 : again])) < 0.5
    assert float(np.median(err[lost + 1 : again])) < 0.3
    yaw = [abs(wrap_angle(r["theta"] - t)) for r, t in zip(rows, truth[:, 2], strict=True)]
    assert max(yaw[lost + 1 : again]) < math.radians(10)


def test_map_counts_every_acknowledged_frame(kidnapped) -> None:
    counts = queries.Summary().answer(kidnapped["session"])["counts"]
    statuses = kidnapped["statuses"]
    lost, again = statuses.index("lost"), statuses.index("relocalised", statuses.index("lost"))
    assert counts["frames"] == len(KEPT)
    assert counts["off_graph_frames"] == again - lost - 1


def test_tum_text_has_every_frame(kidnapped) -> None:
    rows = queries.Trajectory("r1").answer(kidnapped["session"])["r1"]
    lines = [ln for ln in tum_text(rows).splitlines() if ln and not ln.startswith("#")]
    assert len(lines) == len(KEPT)
    stamps = [float(ln.split()[0]) for ln in lines]
    np.testing.assert_allclose(stamps, [r["stamp"] for r in rows], atol=1e-6)


def test_initialising_robot_in_pose_and_trajectory(tmp_path: Path) -> None:
    """r2 drives r1's circle from r1's frame 60 on, without an initial pose."""
    session = _new(tmp_path / "m2.sqlite")
    for f in FRAMES[:60]:
        session.submit(frame_to_dict(f))
    statuses, poses = [], []
    for k in range(30):
        f = dataclasses.replace(FRAMES[60 + k], robot="r2", seq=k, initial_pose=None)
        f = dataclasses.replace(f, odometry=None) if k == 0 else f
        result = json.loads(session.submit(frame_to_dict(f)).result_json)
        statuses.append(result["localisation"]["status"])
        poses.append(queries.Pose().answer(session)["robots"].get("r2"))
        if k == 0:
            rows = queries.Trajectory("r2").answer(session)["r2"]
            assert [(r["seq"], r["source"]) for r in rows] == [(0, "filter")]
    first = statuses.index("relocalised")
    assert first > 0 and set(statuses[:first]) == {"initialising"}
    for k, doc in enumerate(poses[:first]):
        assert doc is not None, "an initialising robot is listed"
        assert doc["seq"] == k and doc["localisation"]["status"] == "initialising"
        assert (doc["pose"] is None) == (doc["covariance"] is None)
        if doc["pose"] is not None:
            assert np.all(np.linalg.eigvalsh(np.array(doc["covariance"])) >= -1e-12)
    assert poses[first - 1]["pose"] is not None  # the filter weighed many frames by then
    assert poses[-1]["localisation"]["status"] == "tracking"
    rows = queries.Trajectory("r2").answer(session)["r2"]
    assert [r["seq"] for r in rows] == list(range(30))
    assert {r.get("source") for r in rows[:first]} == {"odometry"}
    err = [
        math.hypot(r["x"] - TRUTH[60 + k][0], r["y"] - TRUTH[60 + k][1]) for k, r in enumerate(rows)
    ]
    assert max(err[:first]) < 0.5
    session.close()
