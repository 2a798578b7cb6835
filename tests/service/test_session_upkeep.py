"""A map whose upkeep runs after the frame's result (solver.upkeep "after_frame"): its
removals are stored, sent and published with the next frame, exactly once, through
snapshots, reloads and a crash between a frame and its upkeep."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from service.frames_io import frame_to_dict
from service.session import MapSession
from service.settings import StoreSettings
from service.store import MapPlace, MapRecord
from tests.graph._world import circle_frames
from tests.service.conftest import PlaceFactory

FRAMES = [frame_to_dict(f) for f in circle_frames(120, seed=2)[0]]
AFTER = {"landmark_cap": 6, "pose_window": 10, "solver": {"upkeep": "after_frame"}}


def _new(path: Path | MapPlace, config: dict[str, Any], every: int = 1000) -> MapSession:
    record = MapRecord("m1", "test", "mapping", config, time.time())
    return MapSession.create(path, record, StoreSettings(snapshot_every=every))


def _removed(result_json: str) -> list[int]:
    return list(json.loads(result_json)["landmarks"]["marginalised"])


def test_removals_come_with_the_next_frame_once_each(place: PlaceFactory) -> None:
    session = _new(place("m1"), AFTER)
    reported: list[int] = []
    for f in FRAMES:
        reply = session.submit(f)
        reported += _removed(reply.result_json)
        events = [kind for _, kind, _ in reply.events]
        assert events.count("landmark_marginalised") == len(_removed(reply.result_json))
        session.upkeep()  # what the worker does once the result is sent
        assert len(session.slam.landmarks) <= 6
    assert len(reported) > 5, "the run must exercise the budget"
    assert len(set(reported)) == len(reported) or session.slam.restoration_count > 0
    logged = session.store.removals()
    assert len(logged) == len(reported)
    # The last frame's upkeep is reported by the frame after it.
    assert session.slam.removal_count - len(reported) == len(session.slam._unreported)


def test_the_stored_map_does_not_depend_on_when_the_upkeeps_ran(place: PlaceFactory) -> None:
    eager, lazy = _new(place("a"), AFTER), _new(place("b"), AFTER)
    for f in FRAMES:
        a, b = eager.submit(f), lazy.submit(f)
        eager.upkeep()
        assert _removed(a.result_json) == _removed(b.result_json)
        assert json.loads(a.result_json)["pose"] == json.loads(b.result_json)["pose"]
    assert eager.store.removals() == lazy.store.removals()
    assert eager.store.archived() == lazy.store.archived()


def test_a_crash_between_a_frame_and_the_next_loses_no_removal(place: PlaceFactory) -> None:
    """Snapshots taken with an upkeep pending and after it; the process dies after an
    upkeep whose removals no frame reported yet: the reload reports them with the next
    frame, once."""
    path = place("m1")
    session = _new(path, AFTER, every=7)
    reference = _new(place("ref"), AFTER)
    for k, f in enumerate(FRAMES[:80]):
        session.submit(f)
        reference.submit(f)
        if k % 2:
            session.upkeep()
        if session.snapshot_due:
            session.snapshot()
    session.upkeep()
    assert session.slam._unreported or session.slam.removal_count == 0
    session.store.close()  # dies: nothing more written

    reopened = MapSession(path, StoreSettings(snapshot_every=7))
    assert reopened.slam.frame_count == 80
    for f in FRAMES[80:]:
        a, b = reopened.submit(f), reference.submit(f)
        assert _removed(a.result_json) == _removed(b.result_json)
        reopened.upkeep()
    logged = [r["landmark_id"] for r in reopened.store.removals()]
    expected = [r["landmark_id"] for r in reference.store.removals()]
    assert sorted(logged) == sorted(expected) and len(logged) > 5
