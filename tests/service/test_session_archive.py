"""The archive of removed landmarks in a map's store: rows, events, reloads."""

from __future__ import annotations

import json
import pickle
import sqlite3
import time
from pathlib import Path

from service import queries
from service.frames_io import frame_to_dict
from service.pipeline.snapshot import snapshot_pipeline
from service.session import MapSession
from service.settings import StoreSettings
from service.store import MapPlace, MapRecord
from service.store_sqlite import SqliteMapStore
from tests.graph._world import circle_frames
from tests.service.conftest import PlaceFactory

FRAMES = [frame_to_dict(f) for f in circle_frames(140, seed=3, n_landmarks=30)[0]]
CONFIG = {"landmark_cap": 6, "pose_window": 20}


def _new(path: Path | MapPlace, every: int = 50) -> MapSession:
    record = MapRecord("m1", "test", "mapping", CONFIG, time.time())
    return MapSession.create(path, record, StoreSettings(snapshot_every=every))


def _events(session: MapSession, kind: str) -> list[dict]:
    store = session.store
    if isinstance(store, SqliteMapStore):
        query, args = "SELECT data FROM events WHERE kind = ? ORDER BY id", (kind,)
    else:  # PostgreSQL: the map's rows
        query = "SELECT data FROM events WHERE map_id = %s AND kind = %s ORDER BY id"
        args = (session.record.id, kind)
    rows = store._conn.execute(query, args).fetchall()  # type: ignore[attr-defined]
    return [json.loads(r[0]) for r in rows]


def _run(path: Path | MapPlace, frames: list[dict]) -> MapSession:
    session = _new(path)
    for f in frames:
        session.submit(f)
        if session.snapshot_due:
            session.snapshot()
    return session


def test_the_store_holds_the_archive_the_removal_log_and_restore_events(
    place: PlaceFactory,
) -> None:
    session = _run(place("m1"), FRAMES)
    slam = session.slam
    assert slam.restoration_count > 0
    archived = queries.Landmarks("archived").answer(session)
    assert archived == [e.as_dict() for e in sorted(slam.archive, key=lambda e: e.id)]
    assert {a["id"] for a in archived}.isdisjoint(slam.landmarks)
    # every removal is in the log, a landmark removed twice twice
    assert session.store.removal_count() == slam.removal_count
    removed = [r["landmark_id"] for r in session.store.removals()]
    assert len(removed) > len(set(removed))
    assert set(removed) == {a["id"] for a in archived} | (set(removed) & set(slam.landmarks))
    restored = _events(session, "landmark_restored")
    assert len(restored) == slam.restoration_count
    marginalised = _events(session, "landmark_marginalised")
    for event in restored:  # each came back under the id it was removed with
        assert any(
            m["landmark_id"] == event["id"]
            and m["label"] == event["label"]
            and m["frame_id"] < event["frame_id"]
            for m in marginalised
        )
    # the live answer is what it was: live landmarks only, with their clusters
    live = queries.Landmarks().answer(session)
    assert sorted(lm["id"] for lm in live) == sorted(slam.landmarks)
    assert all("cluster" in lm and "removals" not in lm for lm in live)
    session.close()


def test_the_archive_survives_a_reload_from_snapshot_and_from_the_log(
    place: PlaceFactory,
) -> None:
    path = place("m1")
    session = _run(path, FRAMES)
    archive, store_rows = session.slam.archive, queries.Landmarks("archived").answer(session)
    restorations = session.slam.restoration_count
    session.close()

    reopened = MapSession(path, StoreSettings(snapshot_every=50))
    assert reopened.loaded_from_snapshot > 0
    assert [e.id for e in reopened.slam.archive] == [e.id for e in archive]
    assert reopened.slam.restoration_count == restorations
    assert queries.Landmarks("archived").answer(reopened) == store_rows

    # a snapshot from before the archive (version 3) is refused: the log is replayed
    state = pickle.loads(snapshot_pipeline(reopened.pipeline)[0])
    state["version"] = 3
    reopened.store.save_snapshot(reopened._last_log_id, pickle.dumps(state), keep=1)
    reopened.close()
    replayed = MapSession(path, StoreSettings(snapshot_every=50))
    assert replayed.loaded_from_snapshot == 0
    assert sorted(e.id for e in replayed.slam.archive) == sorted(e.id for e in archive)
    assert replayed.slam.restoration_count == restorations
    replayed.close()


def test_an_older_map_file_has_its_removals_moved_into_the_removal_log(tmp_path: Path) -> None:
    path = tmp_path / "old.sqlite"
    SqliteMapStore(path, synchronous="NORMAL").close()
    conn = sqlite3.connect(path)
    conn.execute(
        "INSERT INTO removals (landmark_id, frame, record) VALUES (?, ?, ?)",
        (4, 17, json.dumps({"landmark_id": 4, "label": "x", "frame": 17})),
    )
    conn.commit()
    conn.close()
    store = SqliteMapStore(path, synchronous="NORMAL")
    assert store.removal_count() == 1 and store.removed_labels() == {4: "x"}
    assert store._conn.execute("SELECT count(*) FROM removals").fetchone()[0] == 0
    store.close()
