"""A map's published view answers its reads as the map itself does; the event feed
hands out what the store holds; the balancer picks the move that evens workers out."""

from __future__ import annotations

import pickle
import time

import numpy as np
import pytest

from graph.trajectory import with_final_rows
from service.balance import choose_move
from service.events import Notifier, sse_bytes
from service.frames_io import frame_to_dict
from service.offline.datasets.indoor_sim import make_world, simulate
from service.published import ViewDelta, build_view
from service.queries import Landmarks, Places, Pose, Summary, Trajectory
from service.session import MapSession
from service.settings import StoreSettings
from service.store import MapRecord, Store
from tests.graph._world import circle_frames


@pytest.fixture
def session(store: Store) -> MapSession:
    """A map with enough frames that the estimator made rows final."""
    config = {"landmark_cap": 6, "pose_window": 10}  # poses retire: rows become final
    record = MapRecord("viewmap", "m", "mapping", config, time.time())
    s = MapSession.create(store.place("viewmap"), record, StoreSettings())
    for frame in circle_frames(120, seed=2)[0]:
        s.submit(frame_to_dict(frame))
    yield s
    s.close()


def test_view_answers_every_read_as_the_map(session: MapSession, store: Store) -> None:
    view = build_view(session)
    assert view.log_id == session.last_log_id
    assert store.read_poses("viewmap"), "no final rows: the merge with the store is untested"
    for query in (
        Pose(),
        Summary(),
        Places(),
        Landmarks(),
        Trajectory(),
        Trajectory(robot="r1"),
    ):
        assert query.from_view(view, store) == query.answer(session), query


def test_what_the_view_cannot_answer_goes_to_the_worker(session: MapSession, store: Store) -> None:
    view = build_view(session)
    assert Landmarks("archived").from_view(view, store) is None
    assert Trajectory(stats_every=5).from_view(view, store) is None
    assert Trajectory(robot="nobody").from_view(view, store) is None


def test_after_a_frame_the_costly_parts_lag_until_refreshed(
    session: MapSession, store: Store
) -> None:
    first = build_view(session)
    session.submit(frame_to_dict(circle_frames(121, seed=2)[0][120]))
    second = build_view(session, previous=first, robot="r1")
    assert second.log_id > first.log_id
    assert second.summary == Summary().answer(session)
    assert second.landmarks == first.landmarks and second.landmarks_log_id == first.log_id
    assert second.held is first.held and second.held_log_id == first.log_id
    assert Landmarks().view_behind(second) and not Landmarks().view_behind(first)
    assert Trajectory().view_behind(second) and not Trajectory().view_behind(first)
    assert not Pose().view_behind(second)  # one robot: its pose is all there is
    third = build_view(session, previous=second, refresh=True)
    assert not Landmarks().view_behind(third) and not Trajectory().view_behind(third)
    assert Landmarks().from_view(third, store) == Landmarks().answer(session)
    assert Trajectory().from_view(third, store) == Trajectory().answer(session)


READS = (Pose(), Summary(), Places(), Landmarks(), Trajectory())


def test_a_view_crosses_as_the_parts_that_changed(session: MapSession, store: Store) -> None:
    """What a worker sends after a frame leaves out the documents the view before it
    held (the API process's copy keeps them); applied to that copy, after the pipe's
    pickling, it answers every read as the view itself does. Applied to any other copy,
    it is refused."""
    first = build_view(session)
    whole = ViewDelta.between(first, None)
    held_here = whole.apply(None)  # a whole view needs no base
    assert held_here is not None and held_here.serial == first.serial
    frames = circle_frames(140, seed=2)[0]
    views, kept_places = [first], 0
    for frame in frames[120:]:
        session.submit(frame_to_dict(frame))
        views.append(build_view(session, previous=views[-1], robot="r1"))
        delta = pickle.loads(pickle.dumps(ViewDelta.between(views[-1], views[-2])))
        for part in ("places", "held", "landmarks"):
            kept = getattr(views[-1], part) is getattr(views[-2], part)
            assert (part in delta.fields) != kept, part
        kept_places += "places" not in delta.fields
        assert views[-1].places == Places().answer(session)  # kept only while unchanged
        assert delta.apply(None) is None
        assert delta.apply(first if len(views) > 2 else None) is None
        held_here = delta.apply(held_here)
        assert held_here is not None
        for query in READS:
            assert query.from_view(held_here, store) == query.from_view(views[-1], store), query
    assert kept_places > 0, "every frame changed the places: their reuse is untested"
    assert kept_places < len(frames) - 120, "the places never changed: their renewal untested"


def test_after_one_robots_frame_only_its_pose_is_new(store: Store) -> None:
    """A frame of r1 renews r1's entry of the published poses; r2's stays as of r2's own
    latest frame (its covariance would cost another marginal), and the held rows lag."""
    rng = np.random.default_rng(4)
    world = make_world(rooms=(1, 2), landmarks=30, rng=rng)
    runs = [simulate(world, frames=12, rng=rng, robot=r).frames for r in ("r1", "r2")]
    record = MapRecord("two", "m", "mapping", {"landmark_cap": 20}, time.time())
    session = MapSession.create(store.place("two"), record, StoreSettings())
    try:
        for a, b in zip(*runs, strict=True):
            session.submit(frame_to_dict(a))
            session.submit(frame_to_dict(b))
        before = build_view(session)
        assert before.pose == Pose().answer(session)
        session.submit(frame_to_dict(simulate(world, frames=13, rng=rng).frames[12]))
        after = build_view(session, robot="r1", previous=before)
        now = Pose().answer(session)["robots"]
        assert set(after.pose["robots"]) == set(now) == {"r1", "r2"}
        assert after.pose["robots"]["r1"] == now["r1"]
        assert after.pose["robots"]["r2"] == before.pose["robots"]["r2"]
        assert Pose().view_behind(after) and not Pose().view_behind(before)  # r2 lags
        assert Trajectory().view_behind(after) and not Trajectory().view_behind(before)
    finally:
        session.close()


def test_final_rows_the_view_still_holds_are_not_doubled() -> None:
    final = np.array([[s, s, 0, 0, 0] for s in range(6)], dtype=np.float64)
    held = np.array([[s, s, 1, 1, 1] for s in range(4, 9)], dtype=np.float64)
    rows = with_final_rows(final, held)
    assert rows[:, 0].tolist() == list(range(9))
    assert rows[4:, 2].tolist() == [1.0] * 5  # the held (view's) rows win


def test_final_rows_between_held_ones_are_kept() -> None:
    # A keyframe stays held while the frames after it are made final: held 4, 6, 8
    # among final 0-7.
    final = np.array([[s, s, 0, 0, 0] for s in (0, 1, 2, 3, 5, 7)], dtype=np.float64)
    held = np.array([[s, s, 1, 1, 1] for s in (4, 6, 8)], dtype=np.float64)
    rows = with_final_rows(final, held)
    assert rows[:, 0].tolist() == list(range(9))
    assert rows[:, 2].tolist() == [0, 0, 0, 0, 1, 0, 1, 0, 1]


def test_the_feed_hands_out_events_after_an_id_or_sends_to_the_store() -> None:
    a, b, c, d, g = (
        (i, "frame", name) for i, name in ((1, "a"), (2, "b"), (3, "c"), (4, "d"), (7, "g"))
    )
    feed = Notifier(feed_size=3)
    assert feed.fed_sse("m", 0) is None  # nothing fed: the store
    feed.publish("m", [a, b])
    assert feed.fed_sse("m", 0) == (2, sse_bytes([a, b]))
    assert feed.fed_sse("m", 1) == (2, sse_bytes([b]))
    assert feed.fed_sse("m", 2) == (2, b"")
    feed.publish("m", [c, d])  # the oldest falls out
    assert feed.fed_sse("m", 0) is None
    assert feed.fed_sse("m", 1) == (4, sse_bytes([b, c, d]))
    feed.publish("m", [g])  # a gap (events stored elsewhere): restart
    assert feed.fed_sse("m", 4) is None
    assert feed.fed_sse("m", 6) == (7, sse_bytes([g]))


def test_the_feed_hands_out_sse_bytes_encoded_once() -> None:
    feed = Notifier()
    feed.publish("m", [(1, "frame", '{"a": 1}'), (2, "landmark_added", "{}")])
    assert feed.fed_sse("m", 0) == (
        2,
        b'id: 1\nevent: frame\ndata: {"a": 1}\n\nid: 2\nevent: landmark_added\ndata: {}\n\n',
    )
    assert feed.fed_sse("m", 2) == (2, b"")
    assert feed.fed_sse("other", 0) is None


def test_publish_wakes_the_waiters() -> None:
    feed = Notifier()
    wake = feed.handle("m")
    feed.publish("m", [(1, "frame", "a")])
    assert wake.is_set()


def test_the_balancer_moves_the_map_that_evens_out_the_workers() -> None:
    totals = {0: 24.0, 1: 8.0}
    movable = {0: {"a": 4.0, "b": 4.0, "c": 12.0, "d": 4.0}, 1: {"e": 4.0, "f": 4.0}}
    assert choose_move(totals, movable) == ("a", 0, 1)  # 20:12 (c would give 12:20)
    assert choose_move({0: 16.0, 1: 16.0}, movable) is None
    assert choose_move({0: 10.0, 1: 0.0}, {0: {"big": 10.0}}) is None  # would only swap
    assert choose_move({0: 10.0, 1: 0.0}, {0: {"small": 1.0}}) is None  # gap 10 -> 8
    assert choose_move({0: 10.0, 1: 0.0}, {0: {}}) is None  # nothing may move
    assert choose_move({0: 1.1, 1: 1.0}, {0: {"a": 0.05}}) is None  # within the margin
    assert choose_move({0: 0.004, 1: 0.0}, {0: {"a": 0.002}}) is None  # 4 ms of work
    assert choose_move({0: 17.0, 1: 14.0}, {0: {"a": 1.5}}) is None  # noise, not load
