"""MapSession with a camera: image frames logged durably, replayed, refused cleanly."""

from __future__ import annotations

import json
import pickle
import queue
import sqlite3
import time
from multiprocessing import Pipe
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from frontend.cameras import PanoramaCamera
from service import queries
from service.errors import ServiceError
from service.exchange import export_map, import_frames
from service.offline.datasets.render_run import write_rendered_run
from service.pipeline.images import ImageFrontEnd
from service.session import MapSession
from service.settings import StoreSettings
from service.store import MapRecord

CAMERA = PanoramaCamera(1024, 256)
CONFIG = {
    "landmark_cap": None,
    "pose_window": 30,
    "camera": {"model": "panorama", "width": 1024, "height": 256},
}


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[dict[str, Any], bytes]]:
    """(meta, PNG bytes) of a short rendered run."""
    out = tmp_path_factory.mktemp("rendered")
    rendered = write_rendered_run(
        out, frames=36, rng=np.random.default_rng(5), camera=CAMERA, rooms=(1, 2)
    )
    frames = []
    for line in rendered.frames_path.read_text().splitlines():
        doc = json.loads(line)
        frames.append((doc, (out / doc.pop("image")).read_bytes()))
    return frames


def _new(path: Path, config: dict[str, Any] = CONFIG, every: int = 20) -> MapSession:
    record = MapRecord("cam", "test", "mapping", config, time.time())
    return MapSession.create(path, record, StoreSettings(snapshot_every=every))


def _worst_move(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> float:
    """Largest |dx| + |dy| between two trajectories of the same frames, metres."""
    return max(abs(p["x"] - q["x"]) + abs(p["y"] - q["y"]) for p, q in zip(a, b, strict=True))


def _refused(session: MapSession, meta: dict[str, Any], image: bytes, status: int) -> str:
    frames, logged = session.slam.frame_count, session.store.frame_count()
    with pytest.raises(ServiceError) as info:
        session.submit(meta, image)
    assert info.value.status == status, info.value.detail
    assert session.slam.frame_count == frames and session.store.frame_count() == logged
    return info.value.detail


def test_image_frames_are_logged_with_their_image_and_reload_identically(
    tmp_path: Path, run: list[tuple[dict[str, Any], bytes]]
) -> None:
    path = tmp_path / "cam.sqlite"
    session = _new(path)
    results = []
    for meta, image in run[:30]:
        reply = session.submit(meta, image)
        results.append(json.loads(reply.result_json))
        if session.snapshot_due:
            session.snapshot()
    assert session.vision is not None
    assert len(session.slam.landmarks) > 10, "tracks became landmarks"
    assert sum(len(r["landmarks"]["observed"]) for r in results) > 100
    assert {"features", "features_wait", "association"} <= set(results[-1]["timing_ms"])
    stored = session.store.frames_after(0)
    # The snapshot at frame 20 covers the first 20 frames: their images are pruned.
    assert session.store.frame_image(stored[0].id) is None
    assert session.store.frame_image(stored[-1].id) == run[29][1]
    assert json.loads(stored[0].body)["image"]["bytes"] == len(run[0][1])
    before = queries.Trajectory().answer(session)["r1"]
    live_before = sorted(session.slam.landmarks)
    session.close()

    # Reopen: snapshot at frame 20 (with the front end's state) + 10 image frames replayed.
    reopened = MapSession(path, StoreSettings(snapshot_every=20))
    assert reopened.loaded_from_snapshot == 20
    after = queries.Trajectory().answer(reopened)["r1"]
    assert [p["seq"] for p in after] == [p["seq"] for p in before]
    assert _worst_move(after, before) < 0.02
    assert sorted(reopened.slam.landmarks) == live_before
    # ... and goes on matching the landmarks it knew.
    nxt = json.loads(reopened.submit(*run[30]).result_json)
    assert len(nxt["landmarks"]["observed"]) > 5
    reopened.close()


def test_whole_log_replay_without_snapshot_reproduces_the_map(
    tmp_path: Path, run: list[tuple[dict[str, Any], bytes]]
) -> None:
    path = tmp_path / "cam.sqlite"
    session = _new(path, every=10**6)
    for meta, image in run[:15]:
        session.submit(meta, image)
    before = queries.Trajectory().answer(session)["r1"]
    landmarks = sorted(session.slam.landmarks)
    session.close()
    reopened = MapSession(path, StoreSettings(snapshot_every=10**6))
    assert reopened.loaded_from_snapshot == 0
    assert sorted(reopened.slam.landmarks) == landmarks
    after = queries.Trajectory().answer(reopened)["r1"]
    assert max(abs(a["x"] - b["x"]) for a, b in zip(after, before, strict=True)) < 1e-6
    reopened.close()


def _images_and_trajectory(
    path: Path, run: list[tuple[dict[str, Any], bytes]], settings: StoreSettings
) -> tuple[int, list[dict[str, Any]]]:
    session = MapSession.create(
        path, MapRecord("cam", "test", "mapping", CONFIG, time.time()), settings
    )
    for meta, image in run[:36]:
        session.submit(meta, image)
        if session.snapshot_due:
            session.snapshot()
    count, trajectory = session.store.image_count(), queries.Trajectory().answer(session)["r1"]
    session.close()
    return count, trajectory


def test_images_are_pruned_once_every_kept_snapshot_covers_them(
    tmp_path: Path, run: list[tuple[dict[str, Any], bytes]]
) -> None:
    settings = StoreSettings(snapshot_every=10, snapshots_kept=2)
    path = tmp_path / "cam.sqlite"
    count, before = _images_and_trajectory(path, run, settings)
    # Snapshots at frames 10, 20, 30; the two kept (20, 30) both cover frames 1-20.
    assert count == 36 - 20
    kept, _ = _images_and_trajectory(
        tmp_path / "all.sqlite", run, settings.model_copy(update={"prune_images": False})
    )
    assert kept == 36

    # Snapshot + tail: the tail's images are all there; the map is as it was.
    reopened = MapSession(path, settings)
    assert reopened.loaded_from_snapshot == 30
    after = queries.Trajectory().answer(reopened)["r1"]
    assert [p["seq"] for p in after] == [p["seq"] for p in before]
    assert _worst_move(after, before) < 0.02
    reopened.close()

    # Every snapshot unreadable: the whole log is replayed, the pruned frames from the
    # observations their images gave. The map is rebuilt, though not exactly: the front
    # end did not see those images again, so it learnt none of their descriptors and
    # the tail's images start new landmarks (measured: 0.16 m at worst, |dx| + |dy|).
    conn = sqlite3.connect(path)
    conn.execute("UPDATE snapshots SET state = x'00'")
    conn.commit()
    conn.close()
    rebuilt = MapSession(path, settings)
    assert rebuilt.loaded_from_snapshot == 0 and rebuilt.replay_errors == 0
    again = queries.Trajectory().answer(rebuilt)["r1"]
    assert [p["seq"] for p in again] == [p["seq"] for p in before]
    drift = _worst_move(again, before)
    assert drift < 0.3, drift
    rebuilt.close()


def test_retry_needs_the_same_image(
    tmp_path: Path, run: list[tuple[dict[str, Any], bytes]]
) -> None:
    session = _new(tmp_path / "cam.sqlite")
    for meta, image in run[:3]:
        session.submit(meta, image)
    again = session.submit(*run[2])
    assert again.replayed
    detail = _refused(session, run[2][0], run[3][1], 409)
    assert "seq" in detail
    session.close()


def test_bad_image_frames_leave_the_map_unchanged(
    tmp_path: Path, run: list[tuple[dict[str, Any], bytes]]
) -> None:
    session = _new(tmp_path / "cam.sqlite")
    session.submit(*run[0])
    meta = run[1][0]
    assert "neither PNG nor JPEG" in _refused(session, meta, b"GIF89a....", 422)
    assert "empty" in _refused(session, meta, b"", 422)
    assert "could not be decoded" in _refused(session, meta, run[1][1][:500], 422)
    import cv2

    ok, small = cv2.imencode(".png", np.zeros((100, 400), np.uint8))
    assert ok
    assert "expects 1024x256" in _refused(session, meta, small.tobytes(), 422)
    with_obs = {**meta, "observations": [{"bearing": 0.1, "label": "a"}]}
    assert "meta.observations" in _refused(session, with_obs, run[1][1], 422)
    new_robot = {**meta, "robot": "r2", "seq": 0}
    new_robot.pop("initial_pose", None)
    assert "initial_pose" in _refused(session, new_robot, run[1][1], 422)
    # The map goes on as if nothing happened.
    assert not session.submit(*run[1]).replayed
    assert session.slam.frame_count == 2
    session.close()


def test_map_without_camera_refuses_image_frames(
    tmp_path: Path, run: list[tuple[dict[str, Any], bytes]]
) -> None:
    session = _new(tmp_path / "plain.sqlite", config={"landmark_cap": 10})
    assert "without a camera" in _refused(session, run[0][0], run[0][1], 422)
    session.close()


def test_worker_reader_keeps_arrival_order_and_prefetches_the_features_of_waiting_frames(
    tmp_path: Path, run: list[tuple[dict[str, Any], bytes]]
) -> None:
    from service import worker
    from service.requests import SubmitFrame
    from service.settings import Settings

    # a worker's settings (its frame limits check each posted frame)
    settings = Settings(data_dir=tmp_path / "unused", workers={"nice": 0})
    worker.init_worker(settings.model_dump(mode="json"), 0, own_signals=False)
    session = _new(tmp_path / "cam.sqlite")
    assert session.vision is not None
    worker._sessions["cam"] = session
    api_end, worker_end = Pipe()
    try:
        for k in range(3):
            request = (k, "cam", SubmitFrame(run[k][0], run[k][1]))
            api_end.send_bytes(pickle.dumps(request))
        api_end.close()  # end of file after the three requests
        inbox: queue.Queue[Any] = queue.Queue()
        worker._reader(worker_end, inbox, True)
        queued = [inbox.get_nowait() for _ in range(4)]
        assert queued[3] is None, "end of the connection comes last"
        assert [q[0] for q in queued[:3]] == [0, 1, 2], "read in arrival order"
        assert len(session.vision._prefetched) == 3
        replies = [worker.call(m, request) for _, m, request in queued[:3]]
        assert all(r["ok"] for r in replies), replies
        assert not session.vision._prefetched, "each frame took its own prefetched features"
        assert [json.loads(r["value"].result_json)["seq"] for r in replies] == [
            run[k][0]["seq"] for k in range(3)
        ]
    finally:
        worker._sessions.pop("cam")
        worker._settings = None
        session.close()
        worker_end.close()


def _labels(reply: dict[str, Any], session: MapSession) -> list[str]:
    """Labels of the landmarks a frame's result says it observed."""
    result = json.loads(reply.result_json)
    return sorted(session.slam.landmarks[i].label for i in result["landmarks"]["observed"])


def test_export_import_of_an_image_map_goes_on_associating_as_the_original(
    tmp_path: Path, run: list[tuple[dict[str, Any], bytes]]
) -> None:
    source = _new(tmp_path / "cam.sqlite", every=1000)
    for meta, image in run[:24]:
        source.submit(meta, image)
    doc = json.loads(json.dumps(export_map(source)))  # through JSON, as over HTTP
    image_frames = [f["frame"] for f in doc["frames"]]
    assert all("sha256" in f["image"] and f["observations"] for f in image_frames[1:])
    assert doc["frontend"]["associator"]["landmarks"], "landmark descriptors exported"

    target = _new(tmp_path / "imported.sqlite", every=1000)
    import_frames(target, doc["frames"], doc["frontend"])
    assert sorted(r.label for r in target.slam.landmarks.values()) == sorted(
        r.label for r in source.slam.landmarks.values()
    )
    # New images: the imported map labels them exactly as the original does.
    observed = 0
    for meta, image in run[24:]:
        a, b = source.submit(meta, image), target.submit(meta, image)
        assert _labels(a, source) == _labels(b, target)
        observed += len(_labels(a, source))
    assert observed > 50
    ta, tb = queries.Trajectory().answer(source)["r1"], queries.Trajectory().answer(target)["r1"]
    assert len(ta) == len(tb) == len(run)
    for pa, pb in zip(ta, tb, strict=True):
        assert abs(pa["x"] - pb["x"]) < 1e-6 and abs(pa["y"] - pb["y"]) < 1e-6
    # Its own export round-trips too (observations kept, no images needed).
    again = export_map(target)
    assert [f["frame"]["observations"] for f in again["frames"][:24]] == [
        f["observations"] for f in image_frames
    ]
    source.close()
    target.close()


def test_image_frames_learn_and_recognise_appearance_places_whatever_the_heading(
    tmp_path: Path, run: list[tuple[dict[str, Any], bytes]]
) -> None:
    import cv2

    session = _new(tmp_path / "cam.sqlite")
    results = [json.loads(session.submit(m, i).result_json) for m, i in run[:30]]
    places = queries.Places().answer(session)["appearance_places"]
    assert len(places) >= 2, "the run crosses more than one place spacing"
    assert places[0]["robot"] == "r1" and places[0]["frame"] == 0
    assert results[0]["localisation"]["place"] == 0
    # A place is reported when its score reaches min_score (0.5): near where it was
    # learnt; between places (~0.7 m away in these small rooms) none may be.
    for r in results:
        place, score = r["localisation"]["place"], r["localisation"]["confidence"]
        assert score is not None and (place is not None) == (score >= 0.5)
    assert sum(r["localisation"]["place"] is not None for r in results) >= len(results) // 2
    assert all(r["localisation"]["status"] == "tracking" for r in results)

    # r2 stands where r1 started, turned 90 deg left: its panorama is r1's first one
    # shifted right by a quarter turn (see frontend.appearance's convention).
    meta0, image0 = run[0]
    pano = cv2.imdecode(np.frombuffer(image0, np.uint8), cv2.IMREAD_GRAYSCALE)
    turned = np.roll(pano, CAMERA.width // 4, axis=1)
    ok, png = cv2.imencode(".png", turned)
    assert ok
    start = meta0["initial_pose"]
    meta = {
        **meta0,
        "robot": "r2",
        "seq": 0,
        "initial_pose": {**start, "theta": start["theta"] + np.pi / 2},
    }
    result = json.loads(session.submit(meta, png.tobytes()).result_json)
    assert result["localisation"]["place"] == 0
    assert result["localisation"]["confidence"] > 0.95
    # nothing new learnt
    assert len(queries.Places().answer(session)["appearance_places"]) == len(places)


def test_imported_image_map_reloads_from_its_log_alone(
    tmp_path: Path, run: list[tuple[dict[str, Any], bytes]]
) -> None:
    source = _new(tmp_path / "cam.sqlite", every=1000)
    for meta, image in run[:20]:
        source.submit(meta, image)
    doc = json.loads(json.dumps(export_map(source)))
    path = tmp_path / "imported.sqlite"
    target = _new(path, every=1000)
    import_frames(target, doc["frames"], doc["frontend"])
    target.close()
    # Without its snapshots the map is its log: imported frames replay from their
    # observations and the export's front-end state is put back after them.
    conn = sqlite3.connect(path)
    conn.execute("DELETE FROM snapshots")
    conn.execute("DELETE FROM frontend_states")
    conn.commit()
    conn.close()
    reopened = MapSession(path, StoreSettings(snapshot_every=1000))
    assert reopened.loaded_from_snapshot == 0 and reopened.replay_errors == 0
    for meta, image in run[20:26]:
        a, b = source.submit(meta, image), reopened.submit(meta, image)
        assert _labels(a, source) == _labels(b, reopened)
    source.close()
    reopened.close()


def test_import_refuses_a_bad_front_end_state_and_keeps_nothing(
    tmp_path: Path, run: list[tuple[dict[str, Any], bytes]]
) -> None:
    source = _new(tmp_path / "cam.sqlite")
    for meta, image in run[:6]:
        source.submit(meta, image)
    doc = json.loads(json.dumps(export_map(source)))
    source.close()
    state = doc["frontend"]
    bad_descriptor = json.loads(json.dumps(state))
    bad_descriptor["associator"]["tracks"]["r1"][0]["descriptor"] = "AAAA"
    bad_pose = json.loads(json.dumps(state))
    bad_pose["last"]["r1"]["pose"] = [0.0, "x", 0.0]
    for bad, field in (
        (bad_descriptor, "associator.tracks.r1[0].descriptor"),
        (bad_pose, "frontend.last.r1"),
        ({"associator": 3, "last": {}}, "associator"),
    ):
        target = _new(tmp_path / "imported.sqlite")
        with pytest.raises(ServiceError) as info:
            import_frames(target, doc["frames"], bad)
        assert info.value.status == 422 and field in info.value.detail
        assert target.slam.frame_count == 0 and target.store.frame_count() == 0
        target.close()
    # A frame whose image digest is not one is refused too.
    frames = json.loads(json.dumps(doc["frames"]))
    frames[2]["frame"]["image"] = {"sha256": "nope", "bytes": 3}
    target = _new(tmp_path / "imported2.sqlite")
    with pytest.raises(ServiceError) as info:
        import_frames(target, frames, state)
    assert info.value.status == 422 and "frames[2].frame" in info.value.detail
    target.close()


def _json_frame(meta: dict[str, Any]) -> dict[str, Any]:
    """An image frame's meta as a JSON frame with no bearings (odometry only)."""
    return {**meta, "observations": []}


def _run_with_json_gap(
    path: Path, run: list[tuple[dict[str, Any], bytes]], gap: range
) -> tuple[MapSession, list[dict[str, Any]]]:
    session = _new(path, every=1000)
    results = []
    for k, (meta, image) in enumerate(run[:30]):
        reply = session.submit(_json_frame(meta)) if k in gap else session.submit(meta, image)
        results.append(json.loads(reply.result_json))
    return session, results


def test_json_frames_in_a_camera_map_move_the_front_ends_prediction(
    tmp_path: Path, run: list[tuple[dict[str, Any], bytes]], monkeypatch: pytest.MonkeyPatch
) -> None:
    gap = range(14, 20)  # six frames of odometry only, posted as JSON
    session, results = _run_with_json_gap(tmp_path / "a.sqlite", run, gap)
    assert session.pipeline.images is not None
    # The front end predicts the next image frame from the JSON frame's pose.
    pose, _ = session.pipeline.robots["r1"].pose or (None, None)
    last = results[-1]["pose"]
    np.testing.assert_allclose(pose, [last["x"], last["y"], last["theta"]], atol=1e-9)
    after = results[gap.stop]
    reference = _new(tmp_path / "ref.sqlite", every=1000)
    ref = [json.loads(reference.submit(m, i).result_json) for m, i in run[: gap.stop + 1]]
    assert len(after["landmarks"]["observed"]) >= 10  # measured 14 (36 with images throughout)
    assert abs(after["pose"]["x"] - ref[-1]["pose"]["x"]) < 0.05
    # Reopened from its log (no snapshot), the map predicts the same way.
    session.close()
    reopened = MapSession(tmp_path / "a.sqlite", StoreSettings(snapshot_every=1000))
    restored = reopened.pipeline.robots["r1"].pose
    assert restored is not None
    np.testing.assert_allclose(restored[0], pose, atol=1e-9)
    reopened.close()
    reference.close()
    # Without the JSON frames' poses, the image frame after the gap is predicted from the
    # last image frame plus one frame's odometry, far off, and matches little.
    monkeypatch.setattr(ImageFrontEnd, "note_pose", lambda self, robot, pose, cov: None)
    stale, stale_results = _run_with_json_gap(tmp_path / "b.sqlite", run, gap)
    stale_observed = len(stale_results[gap.stop]["landmarks"]["observed"])
    assert stale_observed <= 0.5 * len(after["landmarks"]["observed"])  # measured 3
    stale.close()


def test_a_robot_may_start_with_a_json_frame_then_send_images(
    tmp_path: Path, run: list[tuple[dict[str, Any], bytes]]
) -> None:
    session = _new(tmp_path / "c.sqlite", every=1000)
    session.submit(_json_frame(run[0][0]))
    meta = {k: v for k, v in run[1][0].items() if k != "initial_pose"}
    result = json.loads(session.submit(meta, run[1][1]).result_json)
    assert result["seq"] == run[1][0]["seq"]
    for meta, image in run[2:8]:
        result = json.loads(session.submit(meta, image).result_json)
    assert len(session.slam.landmarks) > 0 and result["landmarks"]["observed"]
    session.close()
