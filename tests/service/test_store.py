"""The store interface, run against both implementations (SQLite and PostgreSQL):
same answers, same ids, same semantics."""

from __future__ import annotations

import json

import numpy as np
import pytest

from graph.trajectory import PoseRow
from service.keys import key_hash
from service.store import KeyRecord, MapRecord, Store
from service.store_sql import MapStore


def _result(live: int, added: list[int], marginalised: list[int], cov: object) -> str:
    body = {
        "landmarks": {"live": live, "added": added, "marginalised": marginalised},
        "timing_ms": {"total": 2.5},
        "covariance": cov,
    }
    return json.dumps(body, separators=(",", ":"))


@pytest.fixture
def mstore(store: Store) -> MapStore:
    opened = store.place("m1").open()
    opened.set_meta("record", {"id": "m1"})
    return opened


def test_catalog_adds_lists_in_creation_order_and_removes(store: Store) -> None:
    catalog = store.catalog()
    b = MapRecord("b", "second", "mapping", {"landmark_cap": 8}, 2.0)
    a = MapRecord("a", "first", "mapping", {"landmark_cap": None}, 1.0)
    catalog.add(b)
    catalog.add(a)
    assert [r.id for r in catalog.all()] == ["a", "b"]
    assert catalog.get("b") == b and catalog.get("zz") is None
    catalog.set_mode("a", "localisation")
    assert catalog.get("a") == MapRecord("a", "first", "localisation", a.config, 1.0)
    catalog.remove("a")
    assert catalog.all() == [b]
    with pytest.raises(Exception):  # noqa: B017 - sqlite3 / psycopg integrity errors
        catalog.add(b)


def test_catalog_keeps_keys_hashed_and_removes_them_with_their_map(store: Store) -> None:
    catalog = store.catalog()
    for map_id in ("a", "b"):
        catalog.add(MapRecord(map_id, map_id, "mapping", {}, 1.0))
    a_read = KeyRecord("k1", "a", "read", key_hash("csk_secret-one"), 2.0)
    b_write = KeyRecord("k0", "b", "write", key_hash("csk_secret-two"), 2.0)
    a_admin = KeyRecord("k2", "a", "admin", key_hash("csk_secret-three"), 3.0)
    for key in (a_admin, a_read, b_write):
        catalog.add_key(key)
    assert catalog.keys() == [b_write, a_read, a_admin]  # by creation time, then id
    with pytest.raises(Exception):  # noqa: B017 - sqlite3 / psycopg integrity errors
        catalog.add_key(KeyRecord("k3", "b", "read", a_read.hash, 4.0))  # hashes are unique
    catalog.remove_key("k2")
    catalog.remove_key("no-such-key")
    assert catalog.keys() == [b_write, a_read]
    catalog.remove("a")  # the map and its keys
    assert catalog.keys() == [b_write] and [r.id for r in catalog.all()] == ["b"]
    reopened = store.catalog()  # what a restarted API process reads
    assert reopened.keys() == [b_write]


def test_a_place_exists_once_its_map_wrote_and_until_removed(store: Store) -> None:
    place = store.place("m9")
    assert not place.exists()
    opened = place.open()
    opened.set_meta("record", {"id": "m9"})
    assert place.exists()
    opened.append_frame("r1", 1, "{}")
    opened.close()
    place.remove()
    assert not place.exists()
    again = place.open()
    assert again.frame_count() == 0 and again.get_meta("record") is None
    again.close()


def test_meta_round_trips_json(mstore: MapStore) -> None:
    value = {"after": 3, "state": [1.5, "x", None]}
    mstore.set_meta("k", value)
    assert mstore.get_meta("k") == value
    mstore.set_meta("k", 7)
    assert mstore.get_meta("k") == 7 and mstore.get_meta("missing") is None


def test_log_ids_count_per_map_and_robot_seq_is_unique(store: Store, mstore: MapStore) -> None:
    ids = [mstore.append_frame("r1", s, f'{{"seq":{s}}}') for s in (1, 2, 3)]
    other = store.place("m2").open()
    assert other.append_frame("r1", 1, "{}") == 1  # a map's ids are its own
    other.close()
    assert ids == [1, 2, 3]
    with pytest.raises(Exception):  # noqa: B017 - sqlite3 / psycopg integrity errors
        mstore.append_frame("r1", 2, "again")
    assert mstore.frame_count() == 3
    found = mstore.find_frame("r1", 2)
    assert found is not None and (found.id, found.body, found.result) == (2, '{"seq":2}', None)
    assert mstore.find_frame("r2", 2) is None
    mstore.count_attempt(3)
    assert [f.attempts for f in mstore.frames_after(1)] == [0, 1]
    mstore.delete_frame(3)  # the last id is given again, as SQLite's row ids are
    assert mstore.append_frame("r1", 4, "{}") == 3


def test_images_and_their_observations(mstore: MapStore) -> None:
    a = mstore.append_frame("r1", 1, "{}", image=b"\x89PNG\x00a")
    b = mstore.append_frame("r1", 2, "{}", observations='[{"bearing":0.5}]')
    assert mstore.frame_image(a) == b"\x89PNG\x00a" and mstore.frame_image(b) is None
    assert mstore.image_observations(b) == [{"bearing": 0.5}]
    mstore.complete_frame(a, "{}", [], [], observations='[{"bearing":-1}]')
    assert mstore.image_observations(a) == [{"bearing": -1}]
    assert mstore.image_count() == 1
    mstore.delete_frame(a)
    assert mstore.frame_image(a) is None and mstore.image_observations(a) is None


def test_a_completed_frame_stores_result_events_removals_and_poses_together(
    store: Store, mstore: MapStore
) -> None:
    f1 = mstore.append_frame("r1", 1, "{}")
    cov = [[1e-05, 0.0, 0.0], [0.0, 2.5e-3, 0.0], [0.0, 0.0, 1.0]]
    events = mstore.complete_frame(
        f1,
        _result(4, [1, 2], [], cov),
        [("frame", '{"seq":1}'), ("landmark_added", '{"id":1}')],
        [(7, f1, json.dumps({"landmark_id": 7, "label": "14"}))],
        poses=[PoseRow(0, "r1", 1, 10.0, 0.5, -0.25, 3.0)],
    )
    assert events == [1, 2]
    f2 = mstore.append_frame("r1", 2, "{}")
    mstore.complete_frame(
        f2,
        _result(3, [], [1], None),
        [("frame", '{"seq":2}')],
        [(7, f1, "{}"), (1, f2, json.dumps({"landmark_id": 1, "label": "3"}))],
    )
    stored = mstore.find_frame("r1", 1)
    assert stored is not None and stored.result == _result(4, [1, 2], [], cov)
    stats = mstore.frame_stats()
    assert [(s.frame_id, s.live, s.added, s.marginalised) for s in stats] == [
        (1, 4, (1, 2), ()),
        (2, 3, (), (1,)),
    ]
    assert stats[0].total_ms == pytest.approx(2.5)
    assert stats[0].covariance_json is not None and json.loads(stats[0].covariance_json) == cov
    assert stats[1].covariance_json is None
    # a removal is logged once: the second record of landmark 7 in frame 1 is ignored
    assert mstore.removed_labels() == {7: "14", 1: "3"}
    assert mstore.removal_count() == 2
    assert [r["landmark_id"] for r in mstore.removals()] == [7, 1]
    assert [r["landmark_id"] for r in mstore.removals(limit=1)] == [1]
    assert store.read_events("m1", 0) == [
        (1, "frame", '{"seq":1}'),
        (2, "landmark_added", '{"id":1}'),
        (3, "frame", '{"seq":2}'),
    ]
    assert store.read_events("m1", 2) == [(3, "frame", '{"seq":2}')]
    assert store.latest_event_id("m1") == 3 and store.latest_event_id("nobody") == 0


def test_the_removal_log_and_the_archive_follow_removals_and_restorations(
    store: Store, mstore: MapStore
) -> None:
    def record(lid: int, frame: int, label: str) -> str:
        return json.dumps({"landmark_id": lid, "label": label, "frame": frame})

    def entry(lid: int, frame: int) -> tuple[int, int, str]:
        return (lid, frame, json.dumps({"id": lid, "frame": frame}))

    def frame(
        seq: int,
        removals: list[tuple[int, int, str]] | None = None,
        archived: list[tuple[int, int, str]] | None = None,
        restored: list[int] | None = None,
    ) -> None:
        log_id = mstore.append_frame("r1", seq, "{}")
        mstore.complete_frame(
            log_id,
            _result(3, [], [], None),
            [],
            removals or [],
            archived=archived or [],
            restored=restored or [],
        )

    assert mstore.archived() == []
    frame(
        1,
        removals=[(5, 1, record(5, 1, "a")), (2, 1, record(2, 1, "b"))],
        archived=[entry(5, 1), entry(2, 1)],
    )
    assert [a["id"] for a in mstore.archived()] == [2, 5]  # by landmark id
    frame(2, restored=[5])  # landmark 5 leaves the archive
    assert mstore.archived() == [{"id": 2, "frame": 1}]
    # landmark 5 is removed again (a second row in the log) and archived anew;
    # landmark 2 is restored and removed in one frame: its row is replaced
    frame(
        3,
        removals=[(5, 3, record(5, 3, "a")), (2, 3, record(2, 3, "b"))],
        archived=[entry(5, 3), entry(2, 3)],
        restored=[2],
    )
    assert mstore.archived() == [{"id": 2, "frame": 3}, {"id": 5, "frame": 3}]
    assert mstore.removal_count() == 4
    assert mstore.removed_labels() == {5: "a", 2: "b"}
    assert [(r["frame"], r["landmark_id"]) for r in mstore.removals()] == [
        (1, 2),
        (1, 5),
        (3, 2),
        (3, 5),
    ]
    assert [(r["frame"], r["landmark_id"]) for r in mstore.removals(limit=3)] == [
        (1, 5),
        (3, 2),
        (3, 5),
    ]
    # a replayed frame writes the same rows again: nothing changes
    frame(4, removals=[(5, 3, record(5, 3, "a"))], archived=[entry(5, 3)])
    assert mstore.removal_count() == 4 and len(mstore.archived()) == 2
    # another map's rows are its own
    other = store.place("m2").open()
    other.set_meta("record", {"id": "m2"})
    assert other.archived() == [] and other.removal_count() == 0
    other.close()
    mstore.close()
    place = store.place("m1")
    place.remove()
    reopened = place.open()
    assert reopened.archived() == [] and reopened.removal_count() == 0
    reopened.close()


def test_events_are_pruned_to_the_newest_and_ids_keep_growing(
    store: Store, mstore: MapStore
) -> None:
    def add_event(seq: int) -> int:
        frame_id = mstore.append_frame("r", seq, "{}")
        return mstore.complete_frame(frame_id, "{}", [("e", str(seq))], [])[0]

    ids = [add_event(i) for i in range(10)]
    assert ids == list(range(1, 11))
    mstore.prune_events(3)
    assert [e[0] for e in store.read_events("m1", 0)] == [8, 9, 10]
    assert add_event(10) == 11


def test_final_poses_replace_by_robot_and_seq_and_sort_bytewise(mstore: MapStore) -> None:
    rows = [
        PoseRow(0, "r1", 5, 5.0, 1.0, 2.0, 0.1),
        PoseRow(0, "R2", 1, 1.0, 3.0, 4.0, 0.2),
        PoseRow(0, "r1", 2, 2.0, 5.0, 6.0, 0.3),
    ]
    mstore.put_poses(rows)
    mstore.put_poses([PoseRow(0, "r1", 5, 5.0, 9.0, 9.0, 0.9)])
    poses = mstore.poses()
    assert list(poses) == ["R2", "r1"]  # "R" < "r" bytewise, whatever the locale
    np.testing.assert_array_equal(poses["r1"], [[2, 2.0, 5.0, 6.0, 0.3], [5, 5.0, 9.0, 9.0, 0.9]])
    assert list(mstore.poses("R2")) == ["R2"]
    assert mstore.pose_count() == 3
    assert sorted(map(tuple, mstore.pose_positions().tolist())) == [
        (3.0, 4.0),
        (5.0, 6.0),
        (9.0, 9.0),
    ]


def test_snapshots_keep_the_newest_with_their_front_end_state_and_prune_images(
    mstore: MapStore,
) -> None:
    assert mstore.latest_snapshot() is None and mstore.latest_frontend_state() is None
    frames = [mstore.append_frame("r1", s, "{}", image=bytes([s])) for s in range(1, 7)]
    for f in frames:
        mstore.complete_frame(f, "{}", [], [], observations="[]")
    mstore.save_snapshot(2, b"s1", keep=2, frontend=b"f1")
    mstore.save_snapshot(4, b"s2\x00", keep=2, frontend=b"f2")
    mstore.save_snapshot(5, b"s3", keep=2, prune_images=True)
    assert mstore.latest_snapshot() == (5, b"s3")
    assert mstore.latest_frontend_state() is None  # the newest snapshot carries none
    # kept: snapshots up to 4 and 5, so frames 1-4 lose their images
    assert [mstore.frame_image(f) is not None for f in frames] == [False] * 4 + [True] * 2
    mstore.save_snapshot(6, b"s4", keep=1, frontend=b"f4")
    assert mstore.latest_snapshot() == (6, b"s4") and mstore.latest_frontend_state() == b"f4"
    mstore.checkpoint()
