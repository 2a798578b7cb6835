"""The map service under load, with real worker processes: reads are answered while
the map's worker is busy, a map moves between workers without losing a frame, the
balancer moves a map off a crowded worker, and stopping snapshots every map."""

from __future__ import annotations

import asyncio
import json
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from service.frames_io import frame_to_dict
from service.maps import MapService
from service.pipeline.config import MapConfig
from service.queries import Landmarks, Places, Pose, Summary, Trajectory
from service.requests import MapRequest, Ping, RefreshView
from service.session import MapSession
from service.settings import Settings, StoreSettings
from tests.graph._world import circle_frames
from tests.support.snapshots import unsnapshotted

FRAMES = [frame_to_dict(f) for f in circle_frames(60, seed=2)[0]]
CONFIG = MapConfig.model_validate({"landmark_cap": 8})


@dataclass(frozen=True)
class Hold(MapRequest[None]):
    """Keeps the map's worker busy (a long frame) until the file `release` exists;
    creates `started` when it begins."""

    started: str
    release: str

    def answer(self, session: MapSession) -> None:
        Path(self.started).touch()
        deadline = time.monotonic() + 120
        while not Path(self.release).exists() and time.monotonic() < deadline:
            time.sleep(0.01)


def _settings(tmp_path: Path, workers: int) -> Settings:
    return Settings(
        data_dir=tmp_path / "data",
        workers={"count": workers, "nice": 0, "balance_interval_s": 0, "read_ahead": 0},
    )


def _run(tmp_path: Path, workers: int, body: Callable[[MapService], Awaitable[None]]) -> None:
    async def main() -> None:
        service = MapService(_settings(tmp_path, workers))
        await service.start()
        try:
            while not service.ready:
                await asyncio.sleep(0.05)
            await body(service)
        finally:
            await service.stop()

    asyncio.run(main())


async def _new_map(service: MapService, frames: list[dict[str, Any]]) -> str:
    map_id = str((await service.create(name="m", config=CONFIG, mode="mapping"))["id"])
    for f in frames:
        await service.submit(map_id, f)
    return map_id


async def _until(path: Path) -> None:
    deadline = time.monotonic() + 60
    while not path.exists():
        assert time.monotonic() < deadline, f"{path} never appeared"
        await asyncio.sleep(0.01)


def test_reads_are_answered_while_the_worker_is_busy(tmp_path: Path) -> None:
    """One worker, held by a long request on one map with a frame queued behind it: the
    reads of that map and of another map on the same worker are answered meanwhile, and
    the frame's answer brings the new state to the reads."""

    async def body(service: MapService) -> None:
        busy = await _new_map(service, FRAMES[:20])
        idle = await _new_map(service, FRAMES[:10])
        fresh = await _new_map(service, [])  # no frame yet: the view of its creation
        started, release = tmp_path / "started", tmp_path / "release"
        hold = asyncio.create_task(service.query(busy, Hold(str(started), str(release))))
        await _until(started)
        frame = asyncio.create_task(service.submit(busy, FRAMES[20]))
        answers = {}
        for map_id in (busy, idle):
            for query in (Pose(), Landmarks(), Summary(), Places(), Trajectory()):
                answers[map_id, type(query).__name__] = await service.query(map_id, query)
        fresh_summary = await service.summary(fresh)
        assert not hold.done() and not frame.done()  # every read came past them
        assert fresh_summary["counts"]["frames"] == 0
        assert answers[busy, "Pose"]["robots"]["r1"]["seq"] == 19
        assert answers[busy, "Summary"]["counts"]["frames"] == 20
        assert answers[idle, "Summary"]["counts"]["frames"] == 10
        # rows and landmarks may lag behind their map (renewed every few frames, or on
        # demand): what the view has, a part of what the worker has
        rows = answers[idle, "Trajectory"].get("r1", [])
        release.touch()
        await hold
        reply = await frame
        assert json.loads(reply.result_json)["seq"] == 20
        pose = await service.query(busy, Pose())
        assert pose["robots"]["r1"]["seq"] == 20
        # the landmark read during the hold asked for new ones, behind the frame: once
        # the worker is through, the view has them
        expected = await service.pool.call(busy, Landmarks())
        assert expected and await service.query(busy, Landmarks()) == expected
        exact = await service.query(idle, Trajectory())  # the worker is idle: exact
        assert len(exact["r1"]) == 10
        # The view was published with the frame's answer, before the upkeep after it
        # (its removals move the estimate a little; the view is renewed in idle time).
        assert [r["seq"] for r in exact["r1"][: len(rows)]] == [r["seq"] for r in rows]
        for mine, theirs in zip(rows, exact["r1"], strict=False):
            assert math.hypot(mine["x"] - theirs["x"], mine["y"] - theirs["y"]) < 0.01

    _run(tmp_path, 1, body)


def test_a_busy_map_s_lagging_reads_ask_for_new_parts_once_per_interval(
    tmp_path: Path,
) -> None:
    """While the worker is busy, reads that find the landmarks behind are answered from
    the view; they ask the worker for new ones at most once per `api.view_refresh_s`, and
    with 0 at every such read."""

    def refreshes(interval_s: float) -> int:
        asked: list[bool] = []

        async def body(service: MapService) -> None:
            service.settings.api.view_refresh_s = interval_s
            call = service.pool.call

            async def counting(map_id: str, request: Any, **kw: Any) -> Any:
                if isinstance(request, RefreshView):
                    asked.append(request.whole)
                return await call(map_id, request, **kw)

            service.pool.call = counting  # type: ignore[method-assign]
            busy = await _new_map(service, FRAMES[:20])
            for k in range(2):  # twice: a frame, a long request, a frame queued, reads
                started, release = tmp_path / f"started{k}", tmp_path / f"release{k}"
                # the first frame's view has the landmarks behind it; the worker stays busy
                first = asyncio.create_task(service.submit(busy, FRAMES[20 + 2 * k]))
                await asyncio.sleep(0)  # sent first
                hold = asyncio.create_task(service.query(busy, Hold(str(started), str(release))))
                await _until(started)
                second = asyncio.create_task(service.submit(busy, FRAMES[21 + 2 * k]))
                try:
                    await first
                    for _ in range(3):  # from the view, while the worker is busy
                        assert isinstance(await service.query(busy, Landmarks()), list)
                finally:
                    release.touch()
                await hold
                await second
                while service._refreshing:  # the refresh asked for, done
                    await asyncio.sleep(0.01)

        _run(tmp_path / str(interval_s), 1, body)
        return len(asked)

    assert refreshes(60.0) == 1
    assert refreshes(0.0) == 2


def test_a_view_lost_in_the_api_process_comes_back_whole(tmp_path: Path) -> None:
    """A worker sends each view as the parts that changed since the view before it; when
    the API process no longer holds that view, the delta is dropped, the reads go to
    the worker, and the whole view it is asked for answers them again."""

    async def body(service: MapService) -> None:
        map_id = await _new_map(service, FRAMES[:10])
        views: Any = service._views
        views.pop(map_id)
        await service.submit(map_id, FRAMES[10])
        assert map_id not in views  # the frame's delta had no base here
        assert (await service.summary(map_id))["counts"]["frames"] == 11  # the worker's
        deadline = time.monotonic() + 30
        while map_id not in views:
            assert time.monotonic() < deadline, "no whole view came"
            await asyncio.sleep(0.01)
        view = views[map_id]
        assert view.summary["counts"]["frames"] == 11 and view.places is not None
        await service.submit(map_id, FRAMES[11])  # deltas apply again
        assert views[map_id].summary["counts"]["frames"] == 12
        for query in (Pose(), Summary(), Places(), Landmarks(), Trajectory()):
            assert await service.query(map_id, query) == await service.pool.call(map_id, query)

    _run(tmp_path, 1, body)


async def _open_on(service: MapService, worker: int) -> list[str]:
    pool: Any = service.pool
    reply = await pool._request(pool._slots[worker], "", Ping())
    return list(reply["value"]["maps"])


def test_a_map_moves_between_workers_without_losing_a_frame(tmp_path: Path) -> None:
    """A map moved back and forth while its frames arrive: every frame is answered
    once, in order, and a retry of each returns the stored result byte for byte."""

    async def body(service: MapService) -> None:
        map_id = await _new_map(service, [])
        replies: list[str] = []

        async def post() -> None:
            for f in FRAMES:
                replies.append((await service.submit(map_id, f)).result_json)

        posting = asyncio.create_task(post())
        moves = 0
        while not posting.done():
            await asyncio.sleep(0.02)
            target = 1 - service.pool.worker_of(map_id)
            moves += await service.pool.move(map_id, target)  # type: ignore[attr-defined]
        await posting
        assert moves >= 2
        assert [json.loads(r)["seq"] for r in replies] == [f["seq"] for f in FRAMES]
        summary = await service.summary(map_id)
        assert summary["counts"]["frames"] == len(FRAMES)
        for f, first in zip(FRAMES, replies, strict=True):
            again = await service.submit(map_id, f)
            assert again.replayed and again.result_json == first
        owner = service.pool.worker_of(map_id)
        assert map_id in await _open_on(service, owner)
        assert map_id not in await _open_on(service, 1 - owner)  # one writer only

    _run(tmp_path, 2, body)


def test_a_moved_map_is_deleted_where_it_is_open(tmp_path: Path) -> None:
    async def body(service: MapService) -> None:
        map_id = await _new_map(service, FRAMES[:5])
        assert await service.pool.move(map_id, 1 - service.pool.worker_of(map_id))  # type: ignore[attr-defined]
        await service.delete(map_id)
        for worker in (0, 1):
            assert map_id not in await _open_on(service, worker)
        assert not (tmp_path / "data" / "maps" / f"{map_id}.sqlite").exists()

    _run(tmp_path, 2, body)


def test_maps_are_dealt_out_evenly_at_their_first_frame(tmp_path: Path) -> None:
    """Four new maps placed 3:1 on two workers start taking frames together: the first
    frames deal them 2:2 (an empty map moves for free), and every frame is answered in
    order on the map's new worker."""

    async def body(service: MapService) -> None:
        pool: Any = service.pool
        ids = [await _new_map(service, []) for _ in range(4)]
        lone = next(m for m in ids if pool.worker_of(m) == 1)
        crowded = [m for m in ids if m != lone]
        assert await pool.move(crowded[-1], 0)  # 3:1, none with a frame yet
        assert sorted(pool.worker_of(m) for m in ids) == [0, 0, 0, 1]
        moves = pool.moves

        async def post(map_id: str) -> list[int]:
            return [
                json.loads((await service.submit(map_id, f)).result_json)["seq"] for f in FRAMES[:5]
            ]

        answered = await asyncio.gather(*(post(m) for m in ids))
        assert answered == [[f["seq"] for f in FRAMES[:5]]] * 4
        assert sorted(pool.worker_of(m) for m in ids) == [0, 0, 1, 1]
        assert pool.deals == 1 and pool.moves == moves  # a deal is not a balancer move
        for worker in (0, 1):
            open_here = await _open_on(service, worker)
            assert sorted(open_here) == sorted(m for m in ids if pool.worker_of(m) == worker)
        again = await _new_map(service, FRAMES[:1])  # alone: its first frame stays put
        assert pool.deals == 1 and (await service.summary(again))["counts"]["frames"] == 1

    _run(tmp_path, 2, body)


def test_the_balancer_moves_a_map_off_the_busier_worker(tmp_path: Path) -> None:
    async def body(service: MapService) -> None:
        pool: Any = service.pool
        a = await _new_map(service, FRAMES[:1])
        b = await _new_map(service, FRAMES[:1])  # one frame each: dealt already
        if pool.worker_of(a) == pool.worker_of(b):
            pytest_fail = "a new map goes to the less loaded worker"
            raise AssertionError(pytest_fail)
        assert await pool.move(b, pool.worker_of(a))  # both on one worker now
        crowded = pool.worker_of(a)

        async def post(map_id: str) -> None:
            for f in FRAMES[1:40]:
                await service.submit(map_id, f)

        posting = [asyncio.create_task(post(m)) for m in (a, b)]
        await asyncio.sleep(0.5)
        assert await pool.balance(0.5) is None  # one look: the gap must hold for two
        await asyncio.sleep(0.5)
        moved = await pool.balance(0.5)
        await asyncio.gather(*posting)
        assert moved == (a, crowded, 1 - crowded)  # b moved a moment ago: it stays
        assert pool.worker_of(a) != pool.worker_of(b)
        for m in (a, b):
            assert (await service.summary(m))["counts"]["frames"] == 40

    _run(tmp_path, 2, body)


def test_stopping_snapshots_every_map_so_a_start_replays_nothing(tmp_path: Path) -> None:
    ids: list[str] = []
    poses: list[Any] = []

    async def body(service: MapService) -> None:
        for n in (15, 25):  # fewer frames than snapshot_every (200)
            ids.append(await _new_map(service, FRAMES[:n]))
        poses.extend([(await service.query(m, Pose()))["robots"] for m in ids])

    _run(tmp_path, 2, body)
    for map_id, pose in zip(ids, poses, strict=True):
        path = tmp_path / "data" / "maps" / f"{map_id}.sqlite"
        assert unsnapshotted(path) == 0
        session = MapSession(path, StoreSettings())
        try:
            assert session.loaded_from_snapshot == session.last_log_id > 0
            assert Pose().answer(session)["robots"] == pose
        finally:
            session.close()
