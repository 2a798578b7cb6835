"""A real `covslam serve` on a real PostgreSQL, and with `--engine ray` on a real local
two-node Ray cluster: same answers as SQLite, failover that loses and duplicates nothing."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from bench.clusters import LocalRayCluster, PrivatePostgres, Unavailable
from bench.scale_out import check_log, post_until_answered
from tests.e2e.conftest import REPO, Server, create_map, frame_dicts, post_all, sim_frames

FRAMES = frame_dicts(sim_frames(60, seed=3))
SNAPSHOTS = {"COVSLAM_STORE__SNAPSHOT_EVERY": "20"}  # reloads use a snapshot + a log tail


def _trajectory(c: httpx.Client, map_id: str) -> Any:
    r = c.get(f"/v1/maps/{map_id}/trajectory")
    assert r.status_code == 200, r.text
    return r.json()["robots"]


def test_a_postgres_store_serves_the_map_a_sqlite_store_serves(
    tmp_path: Path, postgres: PrivatePostgres
) -> None:
    url = postgres.new_database()
    lite = Server(tmp_path / "lite", env=SNAPSHOTS)
    pg = Server(tmp_path / "pg", env=SNAPSHOTS, args=["--store-url", url])
    lite.start()
    pg.start()
    try:
        with (
            httpx.Client(base_url=lite.url, timeout=60) as a,
            httpx.Client(base_url=pg.url, timeout=60) as b,
        ):
            ma, mb = (
                create_map(a, config={"landmark_cap": 8}),
                create_map(b, config={"landmark_cap": 8}),
            )
            ra, rb = post_all(a, ma, FRAMES), post_all(b, mb, FRAMES)
            assert [r["pose"] for r in ra] == [r["pose"] for r in rb]
            assert _trajectory(a, ma) == _trajectory(b, mb)
            assert not (tmp_path / "pg" / "maps").exists()  # the URL took precedence
        pg.kill9()  # the map comes back from PostgreSQL: snapshot + log tail
        pg.start()
        with httpx.Client(base_url=pg.url, timeout=60) as b:
            assert [m["id"] for m in b.get("/v1/maps").json()] == [mb]
            assert b.get(f"/v1/maps/{mb}").json()["counts"]["frames"] == len(FRAMES)
            again = b.post(f"/v1/maps/{mb}/frames", json=FRAMES[-1])
            assert again.headers.get("idempotent-replayed") == "true"
            assert again.json() == rb[-1]
            with b.stream("GET", f"/v1/maps/{mb}/events", params={"since": 0}) as events:
                first = next(line for line in events.iter_lines() if line.startswith("id:"))
            assert first == "id: 1"
    finally:
        lite.stop()
        pg.stop()


def test_a_postgres_restart_costs_clients_a_retry_and_nothing_else(
    tmp_path: Path, postgres: PrivatePostgres
) -> None:
    server = Server(tmp_path / "data", args=["--store-url", postgres.new_database()])
    server.start()
    try:
        with httpx.Client(base_url=server.url, timeout=60) as c:
            map_id = create_map(c, config={"landmark_cap": 8})
            acked = post_all(c, map_id, FRAMES[:30])
            postgres.restart()  # the worker's and the API's connections are cut
            assert [m["id"] for m in c.get("/v1/maps").json()] == [map_id]
        _post_retrying(server.url, map_id, FRAMES[30:], acked)
        figures = check_log(server.url, map_id, FRAMES, acked)
        assert figures["lost"] == figures["duplicated"] == 0, figures
        assert figures["answer_changed_on_retry"] == 0, figures
        assert "store connection lost" in server.log.read_text()  # the worker reconnected
    finally:
        server.stop()


def test_engine_ray_without_ray_fails_with_one_line(tmp_path: Path) -> None:
    code = (
        "import sys; sys.modules['ray'] = None; from api.cli import main; "
        "sys.exit(main(['serve', '--engine', 'ray', '--port', '0', '--data-dir', sys.argv[1]]))"
    )
    done = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path / "data")],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        "covslam serve: --engine ray needs Ray, which is not installed: pip install 'covslam[ray]'"
    ]


@pytest.fixture(scope="module")
def ray_cluster() -> Iterator[LocalRayCluster]:
    pytest.importorskip("ray", reason="Ray not installed (pip install -e '.[ray]')")
    cluster = LocalRayCluster(nodes=2, cpus=1)
    try:
        cluster.start()
    except Unavailable as exc:
        pytest.skip(f"a local Ray cluster cannot start here: {exc}")
    yield cluster
    cluster.stop()


def _post_retrying(url: str, map_id: str, frames: list[dict], acked: list[dict]) -> None:
    """A client that retries each frame on 503 and transport errors until it is answered."""
    with httpx.Client(base_url=url, timeout=120) as c:
        for f in frames:
            acked.append(post_until_answered(c, map_id, f))


def test_ray_actors_fail_over_without_losing_or_duplicating_a_frame(
    tmp_path: Path, postgres: PrivatePostgres, ray_cluster: LocalRayCluster
) -> None:
    args = ["--engine", "ray", "--ray-address", ray_cluster.address]
    args += ["--store-url", postgres.new_database()]
    api = Server(tmp_path / "a", env=SNAPSHOTS, args=args)
    api.start(timeout_s=180)
    second = Server(tmp_path / "b", env=SNAPSHOTS, args=args)
    try:
        with httpx.Client(base_url=api.url, timeout=120) as c:
            ids = [create_map(c, f"m{i}", config={"landmark_cap": 8}) for i in range(3)]
        acked: list[list[dict]] = [[] for _ in ids]
        clients = [
            threading.Thread(target=_post_retrying, args=(api.url, m, FRAMES, out))
            for m, out in zip(ids, acked, strict=True)
        ]
        for t in clients:
            t.start()
        deadline = time.monotonic() + 120
        while len(acked[0]) < 25 and time.monotonic() < deadline:
            time.sleep(0.05)
        hosts = {w["map"]: w for w in httpx.get(api.url + "/v1/workers").json()["workers"]}
        assert len({w["node"] for w in hosts.values()}) == 2  # spread over both nodes
        t_kill = time.monotonic()
        os.kill(hosts[ids[0]]["pid"], signal.SIGKILL)
        with httpx.Client(base_url=api.url, timeout=120) as c:
            while c.get(f"/v1/maps/{ids[0]}/pose").status_code != 200:
                time.sleep(0.05)
        print(f"map answering again {time.monotonic() - t_kill:.2f} s after the kill")
        for t in clients:
            t.join(timeout=300)
            assert not t.is_alive()
        for map_id, out in zip(ids, acked, strict=True):
            figures = check_log(api.url, map_id, FRAMES, out)
            assert figures["lost"] == figures["duplicated"] == 0, figures
            assert figures["answer_changed_on_retry"] == 0, figures
        status = httpx.get(api.url + "/v1/workers").json()
        assert {w["map"]: w["pid"] for w in status["workers"]}[ids[0]] != hosts[ids[0]]["pid"]
        with httpx.Client(base_url=api.url, timeout=120) as c:
            # maps not killed computed exactly what a map without failover computes
            assert _trajectory(c, ids[1]) == _trajectory(c, ids[2])
        # a second API process serves the same maps (it holds no map state)
        second.start(timeout_s=180)
        with httpx.Client(base_url=second.url, timeout=120) as c2:
            assert sorted(m["id"] for m in c2.get("/v1/maps").json()) == sorted(ids)
            extra = dict(FRAMES[-1], seq=FRAMES[-1]["seq"] + 1, stamp=FRAMES[-1]["stamp"] + 1.0)
            assert c2.post(f"/v1/maps/{ids[1]}/frames", json=extra).status_code == 200
            created = create_map(c2, "from-b", config={"landmark_cap": 8})
        with httpx.Client(base_url=api.url, timeout=120) as c:
            assert c.get(f"/v1/maps/{ids[1]}").json()["counts"]["frames"] == len(FRAMES) + 1
            assert c.get(f"/v1/maps/{created}").status_code == 200
            assert c.delete(f"/v1/maps/{created}").status_code == 204
    finally:
        second.stop()
        api.stop()
