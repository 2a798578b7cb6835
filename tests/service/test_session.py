"""MapSession in-process: durable log, idempotency, snapshot + tail reload."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from service import queries
from service.errors import ServiceError
from service.exchange import export_map
from service.frames_io import canonical_frame, frame_to_dict
from service.session import MapSession
from service.settings import StoreSettings
from service.store import MapPlace, MapRecord
from tests.graph._world import circle_frames
from tests.service.conftest import PlaceFactory

FRAMES = [frame_to_dict(f) for f in circle_frames(90, seed=2)[0]]
# A short window and a small cap: keyframes leave the graph within 120 frames.
RETIRING = {"landmark_cap": 6, "pose_window": 10}


def _new(path: Path | MapPlace, every: int = 25, config: dict | None = None) -> MapSession:
    config = {"landmark_cap": 10, "pose_window": 30} if config is None else config
    record = MapRecord("m1", "test", "mapping", config, time.time())
    return MapSession.create(path, record, StoreSettings(snapshot_every=every))


def test_reopen_from_snapshot_and_tail_answers_as_before(place: PlaceFactory) -> None:
    path = place("m1")
    session = _new(path)
    results = []
    for f in FRAMES[:70]:
        results.append(json.loads(session.submit(f).result_json))
        if session.snapshot_due:  # what the worker does between requests
            session.snapshot()
    before = queries.Trajectory().answer(session)["r1"]
    session.close()

    reopened = MapSession(path, StoreSettings(snapshot_every=25))
    # 70 frames, a snapshot every 25: the reload restored frame 50's and replayed 20
    assert reopened.loaded_from_snapshot == 50
    assert reopened.slam.frame_count == 70
    after = queries.Trajectory().answer(reopened)["r1"]
    assert [p["seq"] for p in after] == [p["seq"] for p in before]
    moved = [
        abs(a["x"] - b["x"]) + abs(a["y"] - b["y"]) for a, b in zip(after, before, strict=True)
    ]
    assert max(moved) < 5e-3
    replay = reopened.submit(FRAMES[40])
    assert replay.replayed and json.loads(replay.result_json) == results[40]
    assert not reopened.submit(FRAMES[70]).replayed


def test_frame_logged_before_a_crash_is_processed_on_reload(place: PlaceFactory) -> None:
    path = place("m1")
    session = _new(path)
    for f in FRAMES[:10]:
        session.submit(f)
    # the process dies after the append, before processing: only the log has the frame
    _, text = canonical_frame(FRAMES[10])
    session.store.append_frame("r1", FRAMES[10]["seq"], text)
    session.close()

    reopened = MapSession(path, StoreSettings())
    assert reopened.slam.frame_count == 11
    stored = reopened.store.find_frame("r1", FRAMES[10]["seq"])
    assert stored is not None and stored.result is not None
    assert json.loads(stored.result)["seq"] == FRAMES[10]["seq"]


def test_duplicates_and_order(place: PlaceFactory) -> None:
    session = _new(place("m1"))
    for f in FRAMES[:5]:
        session.submit(f)
    with pytest.raises(ServiceError) as dup:
        session.submit({**FRAMES[3], "stamp": 99.0})
    assert dup.value.status == 409 and dup.value.slug == "duplicate-seq"
    with pytest.raises(ServiceError) as late:
        session.submit({**FRAMES[6], "seq": 2, "stamp": 1e6})
    assert late.value.status == 409 and late.value.extra["field"] == "seq"
    with pytest.raises(ServiceError) as bad:
        session.submit({**FRAMES[5], "observations": [{"bearing": 9.0, "label": "1"}]})
    assert bad.value.status == 422 and bad.value.extra["field"] == "observations[0].bearing"
    assert session.slam.frame_count == 5 and session.store.frame_count() == 5


def test_a_frame_that_keeps_killing_the_worker_is_dropped(place: PlaceFactory) -> None:
    path = place("m1")
    session = _new(path)
    for f in FRAMES[:5]:
        session.submit(f)
    _, text = canonical_frame(FRAMES[5])
    log_id = session.store.append_frame("r1", FRAMES[5]["seq"], text)
    for _ in range(2):  # two reloads died while processing it
        session.store.count_attempt(log_id)
    session.close()

    reopened = MapSession(path, StoreSettings())
    assert reopened.slam.frame_count == 5
    assert reopened.store.find_frame("r1", FRAMES[5]["seq"]) is None
    assert reopened.replay_errors == 1
    assert not reopened.submit(FRAMES[5]).replayed  # the robot can send it again


def test_a_never_idle_map_is_snapshotted_when_overdue(place: PlaceFactory) -> None:
    path = place("m1")
    session = _new(path, every=10)
    for f in FRAMES[:55]:  # no idle time between requests: no idle snapshot
        session.submit(f)
    session.close()
    reopened = MapSession(path, StoreSettings(snapshot_every=10))
    assert reopened.loaded_from_snapshot == 50  # forced at 5 x snapshot_every
    assert reopened.slam.frame_count == 55


def test_trajectory_stats_agree_with_the_frame_results(place: PlaceFactory) -> None:
    # Cap 9: over these 60 frames a removed landmark comes back (the case counted once).
    session = _new(place("m1"), config={"landmark_cap": 9, "pose_window": 30})
    results = [json.loads(session.submit(f).result_json) for f in FRAMES[:60]]
    plain = queries.Trajectory().answer(session)["r1"]
    rows = queries.Trajectory(stats_every=7).answer(session)["r1"]
    assert [{k: p[k] for k in ("seq", "x", "y")} for p in rows] == [
        {k: p[k] for k in ("seq", "x", "y")} for p in plain
    ]
    assert all("frame_id" not in p for p in plain)
    picked = [i for i, p in enumerate(rows) if "frame_id" in p]
    assert picked == [*range(0, 60, 7), 59]  # every 7th and the latest

    # Labels of every landmark id, from the removal log and the live landmarks.
    label = {r["landmark_id"]: r["label"] for r in session.store.removals()}
    label.update({lm["id"]: lm["label"] for lm in queries.Landmarks().answer(session)})
    removed_labels = [r["label"] for r in session.store.removals()]
    readded = set(removed_labels) & {lm["label"] for lm in queries.Landmarks().answer(session)}
    assert readded, "the run should restore a removed landmark (the case counted once)"
    ids: list[int] = []
    for i, result in enumerate(results):
        # a landmark the budget removes in the frame that initialised it is only in
        # `marginalised`
        for lid in (*result["landmarks"]["added"], *result["landmarks"]["marginalised"]):
            if lid not in ids:
                ids.append(lid)
        if i not in picked:
            continue
        point = rows[i]
        assert point["frame_id"] == result["frame_id"]
        assert point["covariance"] == result["covariance"]
        assert point["live"] == result["landmarks"]["live"]
        assert point["ms"] == result["timing_ms"]["total"]
        assert point["uncapped"] == len({label[lid] for lid in ids})
        assert result["landmarks"]["live"] <= point["uncapped"] <= len(ids)
    # every id the map ever had was counted (ids are never reused)
    assert sorted(ids) == sorted(label)
    # a returning landmark comes back under its id (graph.archive): one id per label
    assert rows[-1]["uncapped"] == len(ids)


@pytest.mark.parametrize("failure", ["estimation", "bug"])
def test_a_frame_the_estimator_fails_on_leaves_the_map_as_it_was(
    place: PlaceFactory, monkeypatch: pytest.MonkeyPatch, failure: str
) -> None:
    """The estimator raising half way through a frame (EstimationError: a 422; any
    other exception, a bug of ours: re-raised for a 500) leaves no trace: the frame is
    not in the log, the map is the one before it, and the same frame is then taken as
    a map that never failed takes it."""
    from graph.errors import EstimationError
    from graph.slam import BearingSlam

    clean = _new(place("clean"))
    expected = [json.loads(clean.submit(f).result_json) for f in FRAMES[:14]]

    session = _new(place("m1"))
    for f in FRAMES[:12]:
        session.submit(f)
    before = queries.Trajectory().answer(session)["r1"]
    real = BearingSlam.process

    failed: list[int] = []

    def half_way(self: BearingSlam, frame, **kwargs):  # type: ignore[no-untyped-def]
        out = real(self, frame, **kwargs)  # the graph takes the frame, then the step fails
        if frame.seq != FRAMES[12]["seq"] or failed:
            return out  # the reload's replay of the log, and the retry, go through
        failed.append(frame.seq)
        if failure == "estimation":
            raise EstimationError("Indeterminate linear system (injected)")
        raise ValueError("Diagonal noise model: sigma values must be non-negative (injected)")

    monkeypatch.setattr(BearingSlam, "process", half_way)
    if failure == "estimation":
        with pytest.raises(ServiceError) as refused:
            session.submit(FRAMES[12])
        assert refused.value.status == 422 and refused.value.slug == "estimation-failed"
    else:
        with pytest.raises(ValueError, match="injected"):
            session.submit(FRAMES[12])
    assert failed

    assert session.store.find_frame("r1", FRAMES[12]["seq"]) is None
    assert session.slam.frame_count == 12
    assert queries.Trajectory().answer(session)["r1"] == before
    got = [json.loads(session.submit(f).result_json) for f in FRAMES[12:14]]
    for a, b in zip(got, expected[12:14], strict=True):
        assert a["seq"] == b["seq"] and a["localisation"] == b["localisation"]
        assert abs(a["pose"]["x"] - b["pose"]["x"]) + abs(a["pose"]["y"] - b["pose"]["y"]) < 5e-3


def test_final_trajectory_rows_are_stored_and_leave_the_estimator(place: PlaceFactory) -> None:
    """A pose that left the graph will not move again: its row goes to the store with
    the frame that finalised it, and neither the estimator nor its snapshots hold it."""
    from graph.slam import BearingSlam
    from graph.snapshot import restore
    from service.pipeline.config import slam_config

    path = place("m1")
    session = _new(path, config=RETIRING)
    frames = circle_frames(120, seed=2)[0]
    for f in frames:
        session.submit(frame_to_dict(f))
        if session.snapshot_due:
            session.snapshot()
    stored, held = session.store.pose_count(), session.slam.held_trajectory_rows
    assert stored > 40 and stored + held == 120
    snap = session.store.latest_snapshot()
    assert snap is not None and restore(snap[1])._trajectory.kept_count == 0

    # The same rows as an estimator that keeps every row itself.
    reference = BearingSlam(
        slam_config(session.record.config, session.record.mode), rng=np.random.default_rng(0)
    )
    for frame in frames:
        reference.process(frame)
    expected = reference.trajectory("r1")["r1"]
    rows = queries.Trajectory().answer(session)["r1"]
    got = np.array([[p["seq"], p["stamp"], p["x"], p["y"], p["theta"]] for p in rows])
    np.testing.assert_array_equal(got, expected)
    assert len(export_map(session)["trajectories"]["r1"]) == 120
    session.close()

    # A reload replays the tail after the snapshot and rewrites the rows it finalises.
    reopened = MapSession(path, StoreSettings(snapshot_every=25))
    assert reopened.loaded_from_snapshot == 100
    assert reopened.store.pose_count() + reopened.slam.held_trajectory_rows == 120
    after = queries.Trajectory().answer(reopened)["r1"]
    assert [p["seq"] for p in after] == [p["seq"] for p in rows]
    assert (
        max(abs(a["x"] - b["x"]) + abs(a["y"] - b["y"]) for a, b in zip(after, rows, strict=True))
        < 5e-3
    )


def test_a_failed_frame_stores_no_final_rows(
    place: PlaceFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The estimator failing half way through a frame that finalised rows: the rows
    are not stored, and the reloaded map holds them again (nothing is lost)."""
    from graph.errors import EstimationError
    from graph.slam import BearingSlam

    session = _new(place("m1"), config=RETIRING)
    frames = [frame_to_dict(f) for f in circle_frames(130, seed=2)[0]]
    for f in frames[:100]:
        session.submit(f)
    real = BearingSlam.process
    failed: list[int] = []

    def half_way(self: BearingSlam, frame, **kwargs):  # type: ignore[no-untyped-def]
        held = self.held_trajectory_rows
        out = real(self, frame, **kwargs)
        if not failed and self.held_trajectory_rows <= held:  # it finalised a row
            failed.append(frame.seq)
            raise EstimationError("injected")
        return out

    monkeypatch.setattr(BearingSlam, "process", half_way)
    for f in frames[100:]:
        before, stored = queries.Trajectory().answer(session)["r1"], session.store.pose_count()
        try:
            session.submit(f)
        except ServiceError:
            break
    assert failed, "no frame finalised a row"
    assert session.store.pose_count() == stored
    assert queries.Trajectory().answer(session)["r1"] == before
    session.submit(frames[failed[0]])
    assert session.store.pose_count() > stored
    assert len(queries.Trajectory().answer(session)["r1"]) == failed[0] + 1


def test_frame_times_keep_the_latest_oldest_first(
    place: PlaceFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The summary's frame times: the last FRAME_TIMES frames' in the order they came,
    across the ring's wrap."""
    import service.session as session_module

    monkeypatch.setattr(session_module, "FRAME_TIMES", 4)
    session = _new(place("m1"))
    before = session.frame_ms()
    assert before.shape == (0,)
    for f in FRAMES[:11]:
        session.submit(f)
        now = session.frame_ms()
        assert len(now) == min(len(before) + 1, 4)
        kept = before[1:] if len(before) == 4 else before
        np.testing.assert_array_equal(now[:-1], kept)
        assert now[-1] > 0
        before = now
    summary = queries.Summary().answer(session)
    assert summary["timing_ms"]["frames"] == 4
    assert summary["timing_ms"]["mean"] == pytest.approx(float(before.mean()))


def test_the_estimator_document_follows_the_config(place: PlaceFactory) -> None:
    """Made once per estimator config (a summary per frame), made anew with the mode's."""
    from service.pipeline.config import slam_config_dict

    session = _new(place("m1"))
    doc = session.estimator_doc()
    assert doc == slam_config_dict(session.slam.config)
    assert session.estimator_doc() is doc
    assert queries.Summary().answer(session)["estimator"] == doc
    session.set_mode("localisation")
    assert session.estimator_doc() == slam_config_dict(session.slam.config)
    assert session.estimator_doc() != doc
