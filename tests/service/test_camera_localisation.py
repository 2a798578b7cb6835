"""Camera robots through the place localiser (service.pipeline): a robot
without initial_pose is relocalised from its images; a kidnapped camera robot goes lost
and recovers; the state survives a snapshot + log tail reload."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from graph.angles import wrap_angle
from graph.localiser import INITIALISING, LOST, RELOCALISED, TRACKING
from service import queries
from service.exchange import export_map, import_frames
from service.offline.datasets.camera_runs import (
    CONFIG,
    Leg,
    mapping_path,
    pose_error,
    render_leg,
    scene,
    start_pose,
    straight,
)
from service.offline.datasets.render import TexturedWorld
from service.session import MapSession
from service.settings import StoreSettings
from service.store import MapRecord

SEED = 7
RELOCALISE_WITHIN = 6
"""Frames a robot starting without a pose may take to be relocalised (3 is the least:
the filter must stay converged for 3 frames)."""


@pytest.fixture(scope="module")
def world() -> TexturedWorld:
    return scene(SEED)


@pytest.fixture(scope="module")
def mapping(world: TexturedWorld) -> Leg:
    """r1 maps the first room from its true initial pose (70 frames)."""
    return render_leg(
        world, mapping_path(), robot="r1", rng=np.random.default_rng([SEED, 1]), initial_pose=True
    )


@pytest.fixture(scope="module")
def newcomer(world: TexturedWorld, mapping: Leg) -> Leg:
    """r2: no initial pose, starts near r1's path at any heading, drives straight."""
    start = start_pose(mapping.truth, np.random.default_rng([SEED, 2]), 0.4)
    return render_leg(world, straight(start, 12), robot="r2", rng=np.random.default_rng(SEED))


def _session(path: Path, every: int = 10**6, cap: int | None = None) -> MapSession:
    config = CONFIG if cap is None else {**CONFIG, "landmark_cap": cap}
    record = MapRecord("cam", "cam", "mapping", config, time.time())
    return MapSession.create(path, record, StoreSettings(snapshot_every=every))


def _post(session: MapSession, leg: Leg, frames: range | None = None) -> list[dict[str, Any]]:
    out = []
    for k in frames if frames is not None else range(len(leg.frames)):
        meta, image = leg.frames[k]
        out.append(json.loads(session.submit(dict(meta), image).result_json))
    return out


def test_a_camera_robot_without_initial_pose_is_relocalised_from_its_images(
    tmp_path: Path, mapping: Leg, newcomer: Leg
) -> None:
    session = _session(tmp_path / "cam.sqlite")
    built = _post(session, mapping)
    assert {r["localisation"]["status"] for r in built} == {TRACKING}
    assert (
        max(pose_error(r["pose"], t)[0] for r, t in zip(built, mapping.truth, strict=True)) < 0.05
    )
    assert len(session.pipeline.localiser.appearance.places) >= 3

    results = _post(session, newcomer)
    statuses = [r["localisation"]["status"] for r in results]
    k = statuses.index(RELOCALISED)
    assert k + 1 <= RELOCALISE_WITHIN, statuses
    assert set(statuses[:k]) == {INITIALISING}
    assert set(statuses[k + 1 :]) == {TRACKING}
    err_m, err_deg = pose_error(results[k]["pose"], newcomer.truth[k])
    assert err_m < 0.3 and err_deg < 10.0, (err_m, err_deg)
    # Tracked by the graph from then on, close to the truth.
    for r, t in zip(results[k:], newcomer.truth[k:], strict=True):
        e_m, e_deg = pose_error(r["pose"], t)
        assert e_m < 0.3 and e_deg < 10.0, (r["seq"], e_m, e_deg)
        assert len(r["landmarks"]["observed"]) > 20
    # The frames before were never in the graph: they carried no landmarks...
    assert all(not r["landmarks"]["observed"] for r in results[:k])
    # ... but none is lost: the trajectory has every frame, the early ones re-expressed
    # from the anchor frame by dead-reckoning backwards.
    rows = queries.Trajectory("r2").answer(session)["r2"]
    assert [row["seq"] for row in rows] == [m["seq"] for m, _ in newcomer.frames]
    for row, t in zip(rows[:k], newcomer.truth[:k], strict=True):
        assert row["source"] == "odometry"
        assert math.hypot(row["x"] - t[0], row["y"] - t[1]) < 0.3
    # The recorded observations of a searching frame are its pose-free matches.
    frames = session.store.frames_after(0)
    first = next(f for f in frames if f.robot == "r2")
    observed = session.store.image_observations(first.id) or []
    assert len(observed) >= 10
    assert all(
        o["label"] in {rec.label for rec in session.slam.landmarks.values()} for o in observed
    )

    # Export / import: the imported map replays the recorded observations through the
    # localiser (no images, so no appearance hints): r2 is relocalised at the same frame.
    doc = json.loads(json.dumps(export_map(session)))
    target = _session(tmp_path / "imported.sqlite")
    import_frames(target, doc["frames"], doc["frontend"])
    imported = [json.loads(f.result or "{}") for f in target.store.frames_after(0)]
    assert [r["localisation"]["status"] for r in imported if r["robot"] == "r2"] == statuses
    moved = [
        math.hypot(a["x"] - b["x"], a["y"] - b["y"])
        for a, b in zip(queries.Trajectory("r2").answer(target)["r2"], rows, strict=True)
    ]
    assert max(moved) < 0.05, moved
    target.close()
    session.close()


def test_a_camera_robot_is_relocalised_where_the_cap_archived_the_landmarks(
    tmp_path: Path, mapping: Leg, newcomer: Leg
) -> None:
    """A cap of 30: by the time r2 starts most landmarks are archived; the localiser
    matches them by the views the front end archived with them, at their archived
    positions."""
    session = _session(tmp_path / "cam.sqlite", cap=30)
    _post(session, mapping)
    live = {rec.label for rec in session.slam.landmarks.values()}
    archived = {entry.label for entry in session.slam.archive}
    assert len(live) <= 30 and len(archived) > 3 * len(live)
    assert session.pipeline.images is not None
    assert session.pipeline.images.front_end.associator.archived_landmarks == len(archived)

    results = _post(session, newcomer)
    statuses = [r["localisation"]["status"] for r in results]
    k = statuses.index(RELOCALISED)
    assert k + 1 <= RELOCALISE_WITHIN, statuses
    for r, t in zip(results[k:], newcomer.truth[k:], strict=True):
        e_m, e_deg = pose_error(r["pose"], t)
        assert e_m < 0.3 and e_deg < 10.0, (r["seq"], e_m, e_deg)
    # The searching frames' pose-free matches are mostly archived landmarks.
    first = next(f for f in session.store.frames_after(0) if f.robot == "r2")
    observed = [o["label"] for o in session.store.image_observations(first.id) or []]
    assert len(observed) >= 10
    assert sum(label in archived for label in observed) > len(observed) / 2
    session.close()


@pytest.mark.parametrize("cap", [None, 40, 30], ids=["uncapped", "cap40", "cap30"])
def test_a_kidnapped_camera_robot_goes_lost_and_recovers(
    tmp_path: Path, world: TexturedWorld, mapping: Leg, cap: int | None
) -> None:
    """With a cap of 40 most landmarks are archived and a tracked frame matches ~17:
    the kidnap must still starve the frames until the filter finds the robot. At cap 30
    a frame matches ~12, fewer than the starvation floor of a map of many landmarks."""
    session = _session(tmp_path / "cam.sqlite", cap=cap)
    _post(session, mapping)
    end = mapping.truth[-1]
    before = straight(end, 8)
    target = mapping.truth[12].copy()  # a pose ~1.2 m from the start, seen while mapping
    target[2] = wrap_angle(math.atan2(3.0 - target[1], 3.0 - target[0]))
    truth = np.vstack([before, straight(target, 30)])
    jump = len(before)
    leg = render_leg(
        world,
        truth,
        robot="r1",
        rng=np.random.default_rng([SEED, 5]),
        first_seq=len(mapping.frames),
        moved_before=True,
        jumps=frozenset({jump}),
    )
    assert math.hypot(*(target[:2] - before[-1][:2])) > 2.0
    results = _post(session, leg)
    statuses = [r["localisation"]["status"] for r in results]
    assert set(statuses[:jump]) == {TRACKING}, "no false alarm before the jump"
    lost = statuses.index(LOST)
    assert jump <= lost <= jump + 12, statuses
    back = statuses.index(RELOCALISED, lost)
    assert back <= lost + 10, statuses
    assert set(statuses[back + 1 :]) == {TRACKING}
    for r, t in zip(results[back:], truth[back:], strict=True):
        e_m, e_deg = pose_error(r["pose"], t)
        assert e_m < 0.3 and e_deg < 10.0, (r["seq"], e_m, e_deg)
    assert session.pipeline.localiser.localiser.robots["r1"].lost_count == 1

    # A robot in the second room, which nobody mapped: its pose-free matches are
    # look-alikes; it must stay initialising rather than be relocalised somewhere wrong.
    unmapped = render_leg(
        world, straight(np.array([3.0, 9.0, 0.3]), 12), robot="u", rng=np.random.default_rng(1)
    )
    statuses = [r["localisation"]["status"] for r in _post(session, unmapped)]
    assert set(statuses) == {INITIALISING}, statuses
    session.close()


def test_a_searching_camera_robot_survives_a_snapshot_and_log_tail_reload(
    tmp_path: Path, mapping: Leg, newcomer: Leg
) -> None:
    path = tmp_path / "cam.sqlite"
    session = _session(path)
    _post(session, mapping)
    first = _post(session, newcomer, range(1))
    assert first[0]["localisation"]["status"] == INITIALISING
    session.snapshot()  # the filter of r2 is in the snapshot ...
    _post(session, newcomer, range(1, 2))  # ... and this frame in the log's tail
    pf = session.pipeline.localiser.localiser.robots["r2"].pf
    particles, weights = pf.particles.copy(), pf.log_weights.copy()
    assert session.pipeline.images is not None
    assert session.pipeline.images.last_pose("r2") is None, (
        "the front end does not track a searching robot"
    )
    session.close()

    reopened = MapSession(path, StoreSettings(snapshot_every=10**6))
    assert reopened.loaded_from_snapshot > 0
    again = reopened.pipeline.localiser.localiser.robots["r2"].pf
    assert np.array_equal(again.particles, particles)
    assert np.array_equal(again.log_weights, weights)
    results = _post(reopened, newcomer, range(2, len(newcomer.frames)))
    statuses = [r["localisation"]["status"] for r in results]
    k = statuses.index(RELOCALISED)
    assert k + 3 <= RELOCALISE_WITHIN
    e_m, e_deg = pose_error(results[k]["pose"], newcomer.truth[k + 2])
    assert e_m < 0.3 and e_deg < 10.0
    assert queries.Pose().answer(reopened)["robots"]["r2"]["localisation"]["status"] == TRACKING
    reopened.close()


def test_a_new_camera_robot_needs_initial_pose_while_the_map_has_no_landmarks(
    tmp_path: Path, newcomer: Leg
) -> None:
    from service.errors import ServiceError

    session = _session(tmp_path / "cam.sqlite")
    with pytest.raises(ServiceError) as info:
        session.submit(dict(newcomer.frames[0][0]), newcomer.frames[0][1])
    assert info.value.status == 422 and "no landmarks" in info.value.detail
    assert session.store.frame_count() == 0
    session.close()
