"""A worker's create, delete and failed import leave each store (SQLite, PostgreSQL)
clean: what the API's failed-create cleanup relies on."""

from __future__ import annotations

import pickle
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from service import worker
from service.exchange import Export
from service.frames_io import frame_to_dict
from service.queries import Summary
from service.requests import CreateMap, DeleteMap, ImportMap, MapRequest, SubmitFrame
from service.session import MapSession
from service.settings import Settings
from service.store import MapRecord, Store
from tests.graph._world import circle_frames
from tests.support.clusters import PrivatePostgres

FRAMES = [frame_to_dict(f) for f in circle_frames(5, seed=2)[0]]


@pytest.fixture(params=["sqlite", "postgresql"])
def store_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    if request.param == "sqlite":
        return str(tmp_path / "store")
    server: PrivatePostgres = request.getfixturevalue("postgres")
    return server.new_database()


@pytest.fixture
def in_process_worker(store_url: str, tmp_path: Path) -> Iterator[Store]:
    """This process as a worker of the store; the store as the API process sees it."""
    settings = Settings(
        data_dir=tmp_path / "unused",
        store={"url": store_url},
        workers={"nice": 0},
    )
    worker.init_worker(settings.model_dump(mode="json"), 0, own_signals=False)
    store = settings.open_store()
    yield store
    for map_id in list(worker._sessions):
        worker.call(map_id, DeleteMap())
    if worker._store is not None:
        worker._store.close()
    worker._store = worker._settings = None
    store.close()


def _record(map_id: str) -> MapRecord:
    return MapRecord(map_id, "m", "mapping", {"landmark_cap": 8}, time.time())


def test_delete_removes_a_created_map_from_the_store(in_process_worker: Store) -> None:
    created = worker.call("m1", CreateMap(_record("m1").as_dict()))
    assert created["ok"], created
    for frame in FRAMES:
        assert worker.call("m1", SubmitFrame(frame))["ok"]
    assert in_process_worker.place("m1").exists()
    assert worker.call("m1", DeleteMap())["ok"]
    assert not in_process_worker.place("m1").exists()
    assert in_process_worker.read_events("m1", 0) == []


def test_a_failed_import_leaves_nothing_behind(
    in_process_worker: Store, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert worker.call("src", CreateMap(_record("src").as_dict()))["ok"]
    for frame in FRAMES:
        assert worker.call("src", SubmitFrame(frame))["ok"]
    exported = worker.call("src", Export())
    assert exported["ok"], exported

    def fail(session: MapSession, frames: object, frontend: object) -> None:
        raise RuntimeError("replay failed")

    monkeypatch.setattr(worker, "import_frames", fail)
    reply = worker.call("dst", ImportMap(exported["value"], time.time(), 8))
    assert reply["ok"] is False and reply["error"]["status"] == 500
    assert not in_process_worker.place("dst").exists()
    assert in_process_worker.place("src").exists()


def test_a_query_is_a_class_the_worker_answers_without_a_routing_table(
    in_process_worker: Store,
) -> None:
    """A new query is a MapRequest with its `answer`: the worker carries it out as it is,
    and it crosses the process boundary pickled."""

    assert worker.call("q", CreateMap(_record("q").as_dict()))["ok"]
    for frame in FRAMES:
        assert worker.call("q", SubmitFrame(frame))["ok"]
    request = pickle.loads(pickle.dumps(_RobotsSeen()))
    assert worker.call("q", request) == {"ok": True, "value": ["r1"]}
    summary = worker.call("q", pickle.loads(pickle.dumps(Summary())))["value"]
    assert summary["counts"]["frames"] == len(FRAMES) and summary["robots"] == ["r1"]


@dataclass(frozen=True)
class _RobotsSeen(MapRequest[list[str]]):
    def answer(self, session: MapSession) -> list[str]:
        return sorted(session.pipeline.last_accepted())
