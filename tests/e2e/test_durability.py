"""Durability and availability of a real `covslam serve`: kill -9 of the whole service,
a crashed worker, and the API's responsiveness while a worker computes."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from service.session import MapSession
from service.settings import StoreSettings
from service.store import MapRecord
from service.store_sqlite import SqliteCatalog, map_db_path
from tests.e2e.conftest import Server, create_map, frame_dicts, post_all, sim_frames

FRAMES = frame_dicts(sim_frames(260, seed=7))


def _poster(url: str, map_id: str, frames: list[dict], acked: dict[int, dict]) -> None:
    """Post frames in order until the service disappears; record every acknowledged one."""
    with httpx.Client(base_url=url, timeout=30) as c:
        for f in frames:
            try:
                r = c.post(f"/v1/maps/{map_id}/frames", json=f)
            except httpx.TransportError:
                return
            if r.status_code != 200:
                return
            acked[f["seq"]] = r.json()


def test_kill9_at_random_moments_loses_no_acknowledged_frame(tmp_path: Path) -> None:
    server = Server(
        tmp_path / "data", env={"COVSLAM_STORE__SNAPSHOT_EVERY": "40"}
    )  # snapshots + log tails are both exercised
    server.start()
    rng = np.random.default_rng(11)
    acked: dict[int, dict] = {}
    recoveries = []
    try:
        with httpx.Client(base_url=server.url, timeout=30) as c:
            map_id = create_map(c, "durable", config={"landmark_cap": 8})
            reference = create_map(c, "reference", config={"landmark_cap": 8})
        for _ in range(3):
            todo = [f for f in FRAMES if f["seq"] not in acked]
            thread = threading.Thread(target=_poster, args=(server.url, map_id, todo, acked))
            thread.start()
            time.sleep(float(rng.uniform(0.2, 1.2)))
            server.kill9()
            thread.join(timeout=30)
            assert not thread.is_alive()
            recoveries.append(server.start())
            with httpx.Client(base_url=server.url, timeout=30) as c:
                traj = c.get(f"/v1/maps/{map_id}/trajectory").json()["robots"].get("r1", [])
                present = {p["seq"] for p in traj}
                assert set(acked) <= present, sorted(set(acked) - present)
                # present but unacknowledged: at most the frame in flight at the kill
                assert len(present - set(acked)) <= 1
                for seq in sorted(acked)[-5:]:
                    again = c.post(f"/v1/maps/{map_id}/frames", json=FRAMES[seq])
                    assert again.status_code == 200
                    assert again.headers.get("idempotent-replayed") == "true"
                    assert again.json() == acked[seq]
        with httpx.Client(base_url=server.url, timeout=30) as c:
            rest = [f for f in FRAMES if f["seq"] not in acked]
            for f in rest:
                r = c.post(f"/v1/maps/{map_id}/frames", json=f)
                assert r.status_code == 200, r.text
            post_all(c, reference, FRAMES)
            a = c.get(f"/v1/maps/{map_id}").json()["counts"]
            b = c.get(f"/v1/maps/{reference}").json()["counts"]
            assert a["frames"] == b["frames"] == len(FRAMES)
            pa = c.get(f"/v1/maps/{map_id}/pose").json()["robots"]["r1"]["pose"]
            pb = c.get(f"/v1/maps/{reference}/pose").json()["robots"]["r1"]["pose"]
            # restored maps re-solve iSAM2 from the snapshot's linearisation point: close,
            # not bit-identical to the map that never stopped
            assert abs(pa["x"] - pb["x"]) < 0.1 and abs(pa["y"] - pb["y"]) < 0.1, (pa, pb)
        print(
            f"kill -9 x3: {len(acked)} acked before kills; ready again in "
            f"{', '.join(f'{t:.2f}' for t in recoveries)} s"
        )
    finally:
        server.stop()


@pytest.fixture(scope="module")
def busy_server(tmp_path_factory: pytest.TempPathFactory):
    server = Server(tmp_path_factory.mktemp("crash") / "data")
    server.start()
    yield server
    server.stop()


def _import_in_background(url: str, doc: dict, out: list[httpx.Response]) -> threading.Thread:
    def run() -> None:
        with httpx.Client(base_url=url, timeout=120) as c:
            out.append(c.post("/v1/maps/import", json=doc))

    thread = threading.Thread(target=run)
    thread.start()
    return thread


def test_health_probe_answers_within_50ms_during_a_heavy_replay(busy_server: Server) -> None:
    with httpx.Client(base_url=busy_server.url, timeout=30) as c:
        map_id = create_map(c, "heavy", config={"landmark_cap": 8})
        post_all(c, map_id, FRAMES)
        doc = c.get(f"/v1/maps/{map_id}/export").json()
        replies: list[httpx.Response] = []
        threads = [_import_in_background(busy_server.url, doc, replies) for _ in range(2)]
        latencies = []
        time.sleep(0.1)
        with httpx.Client(base_url=busy_server.url, timeout=5) as probe:
            while any(t.is_alive() for t in threads):
                t0 = time.perf_counter()
                assert probe.get("/healthz").status_code == 200
                latencies.append(1e3 * (time.perf_counter() - t0))
                time.sleep(0.02)
        for t in threads:
            t.join()
        assert len(replies) == 2 and all(r.status_code == 201 for r in replies), [
            r.text for r in replies
        ]
    ms = np.asarray(latencies)
    print(
        f"healthz during 2 imports ({len(ms)} probes): p50 {np.median(ms):.1f} ms, "
        f"p99 {np.percentile(ms, 99):.1f} ms, max {ms.max():.1f} ms"
    )
    assert len(ms) >= 20, "the replay must last long enough to probe"
    # p99, not the max: on a 2-core machine with other work beside the suite a single
    # probe is now and then descheduled for a few hundred ms (339 ms once, p99 13 ms),
    # which says nothing about the event loop. A probe queued behind an import would
    # wait seconds, and hold every later probe with it.
    assert np.percentile(ms, 99) < 50.0


def test_worker_crash_answers_503_with_retry_after_then_recovers(busy_server: Server) -> None:
    with httpx.Client(base_url=busy_server.url, timeout=30) as c:
        map_id = create_map(c, "survivor", config={"landmark_cap": 8})
        post_all(c, map_id, FRAMES[:200])  # its import replays 200 frames: ~1-2 s in flight
        before = c.get(f"/v1/maps/{map_id}/pose").json()
        doc = c.get(f"/v1/maps/{map_id}/export").json()
        replies: list[httpx.Response] = []
        thread = _import_in_background(busy_server.url, doc, replies)
        time.sleep(0.3)
        for pid in busy_server.worker_pids():
            os.kill(pid, signal.SIGKILL)
        thread.join(timeout=60)
        assert replies and replies[0].status_code == 503, replies[0].text if replies else None
        assert int(replies[0].headers["retry-after"]) >= 1
        assert replies[0].headers["content-type"].startswith("application/problem+json")

        t0 = time.perf_counter()
        busy_server.wait_ready(timeout_s=60)
        recovered = c.get(f"/v1/maps/{map_id}/pose")
        recovery_s = time.perf_counter() - t0
        assert recovered.status_code == 200
        after = recovered.json()["robots"]["r1"]
        assert after["seq"] == before["robots"]["r1"]["seq"]
        assert abs(after["pose"]["x"] - before["robots"]["r1"]["pose"]["x"]) < 0.05
        r = c.post(f"/v1/maps/{map_id}/frames", json=FRAMES[200])
        assert r.status_code == 200, r.text
        status = c.get("/readyz").json()
        assert status["worker_restarts"] >= 1
        assert "covslam_worker_restarts_total" in c.get("/metrics").text
        print(f"worker crash: ready and answering again {recovery_s:.2f} s after the 503")


def test_readyz_is_503_until_the_maps_are_loaded(tmp_path: Path) -> None:
    """A store whose map has a long log and no snapshot: the service answers /healthz at
    once, /readyz 503 while the worker replays the log, then 200 with the map intact."""
    data = tmp_path / "data"
    record = MapRecord("longlog", "long log", "mapping", {"landmark_cap": 8}, time.time())
    session = MapSession.create(
        map_db_path(data, record.id), record, StoreSettings(snapshot_every=100_000)
    )
    for f in FRAMES[:150]:
        session.submit(f)
    session.close()
    SqliteCatalog(data, synchronous="NORMAL").add(record)

    server = Server(data, env={"COVSLAM_STORE__SNAPSHOT_EVERY": "100000"})
    server.start(wait_ready=False)
    statuses = []
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                assert httpx.get(server.url + "/healthz", timeout=5).status_code == 200
                statuses.append(httpx.get(server.url + "/readyz", timeout=5).status_code)
            except httpx.TransportError:
                time.sleep(0.05)
                continue
            if statuses[-1] == 200:
                break
            time.sleep(0.02)
        assert statuses and statuses[0] == 503 and statuses[-1] == 200, statuses
        with httpx.Client(base_url=server.url, timeout=30) as c:
            assert c.get("/v1/maps/longlog").json()["counts"]["frames"] == 150
    finally:
        server.stop()
