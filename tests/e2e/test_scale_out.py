"""A real `covslam serve` on a real PostgreSQL, and with `--engine ray` on a real local
two-node Ray cluster: same answers as SQLite, failover that loses and duplicates nothing."""

from __future__ import annotations

import os
import shutil
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

from service.offline.http_client import check_log, post_until_answered
from tests.e2e.conftest import REPO, Server, create_map, frame_dicts, post_all, sim_frames
from tests.support.clusters import LocalRayCluster, PrivatePostgres, Unavailable

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


def _compose() -> list[str]:
    """The compose command there is (v2 plugin or v1), or skip."""
    plugin = subprocess.run(["docker", "compose", "version"], capture_output=True, check=False)
    if shutil.which("docker") and plugin.returncode == 0:
        return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    pytest.skip("no docker compose (apt-get install docker-compose)")


def test_the_scale_compose_file_runs_ray_and_postgres() -> None:
    compose = [*_compose(), "-f", str(REPO / "docker/compose.scale.yaml")]
    env = {**os.environ, "COVSLAM_AUTH__ADMIN_KEY": "k" * 20, "POSTGRES_PASSWORD": "pw"}
    services = subprocess.run([*compose, "config", "--services"], env=env, capture_output=True,
                              text=True, timeout=60, check=True)  # fmt: skip
    assert sorted(services.stdout.split()) == ["covslam", "postgres", "ray-head", "ray-worker"]
    config = subprocess.run([*compose, "config"], env=env, capture_output=True, text=True,
                            timeout=60, check=True).stdout  # fmt: skip
    assert "covslam serve --engine ray --ray-address auto" in config
    assert "postgresql://covslam:pw@postgres:5432/covslam" in config
    del env["POSTGRES_PASSWORD"]  # refused without a database password
    refused = subprocess.run([*compose, "config"], env=env, capture_output=True, text=True,
                             timeout=60, check=False)  # fmt: skip
    assert refused.returncode != 0 and "set a database password" in refused.stderr


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


# The head declares a node dead after 5 failed health checks 1 s apart (Ray's default:
# 3 s apart), so the lost node's maps move sooner; a check still has 2 s to answer, so a
# loaded machine does not lose a live node.
FAST_HEALTH_CHECKS = {
    "RAY_health_check_initial_delay_ms": "1000",
    "RAY_health_check_period_ms": "1000",
    "RAY_health_check_timeout_ms": "2000",
    "RAY_health_check_failure_threshold": "5",
}


@pytest.fixture(scope="module")
def ray_cluster() -> Iterator[LocalRayCluster]:
    pytest.importorskip("ray", reason="Ray not installed (pip install -e '.[ray]')")
    cluster = LocalRayCluster(nodes=2, cpus=1, env=FAST_HEALTH_CHECKS)
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


def _post_in_phases(
    url: str, map_id: str, acked: list[dict], pauses: dict[int, threading.Barrier]
) -> None:
    """`_post_retrying` of FRAMES, meeting the test at `pauses[k]` before frame k (the
    test injects a fault as the clients go on)."""
    with httpx.Client(base_url=url, timeout=120) as c:
        for k, f in enumerate(FRAMES):
            if k in pauses:
                pauses[k].wait(timeout=300)
            acked.append(post_until_answered(c, map_id, f))


def _answers_from_elsewhere(url: str, map_id: str, gone: set[int]) -> None:
    """Wait until the map answers from a process other than those in `gone`."""
    with httpx.Client(base_url=url, timeout=120) as c:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline:
            if c.get(f"/v1/maps/{map_id}/pose").status_code == 200:
                pids = {w["map"]: w["pid"] for w in c.get("/v1/workers").json()["workers"]}
                if pids.get(map_id) not in gone | {None}:
                    return
            time.sleep(0.05)
    raise AssertionError(f"map {map_id} did not answer from a new process")


def test_ray_actors_fail_over_without_losing_or_duplicating_a_frame(
    tmp_path: Path, postgres: PrivatePostgres, ray_cluster: LocalRayCluster
) -> None:
    """4 maps on two nodes, 4 clients posting; kill -9 of map 0's actor process, then
    the second node lost (every process of it SIGKILLed): nothing lost or duplicated."""
    args = ["--engine", "ray", "--ray-address", ray_cluster.address]
    args += ["--store-url", postgres.new_database()]
    # an actor reserving CPU is spread round-robin (one of 0 CPUs goes to a random node);
    # the head (1 CPU) has room for all five maps once the second node is gone
    env = {**SNAPSHOTS, "COVSLAM_RAY__ACTOR_CPUS": "0.2"}
    api = Server(tmp_path / "a", env=env, args=args)
    api.start(timeout_s=180)
    second = Server(tmp_path / "b", env=env, args=args)
    try:
        with httpx.Client(base_url=api.url, timeout=120) as c:
            ids = [create_map(c, f"m{i}", config={"landmark_cap": 8}) for i in range(4)]
        acked: list[list[dict]] = [[] for _ in ids]
        kill_worker, lose_node = (threading.Barrier(len(ids) + 1) for _ in range(2))
        clients = [
            threading.Thread(
                target=_post_in_phases, args=(api.url, m, out, {20: kill_worker, 40: lose_node})
            )
            for m, out in zip(ids, acked, strict=True)
        ]
        for t in clients:
            t.start()

        kill_worker.wait(timeout=300)  # (a) kill -9 the process hosting map 0's actor
        hosts = {w["map"]: w for w in httpx.get(api.url + "/v1/workers").json()["workers"]}
        assert len({w["node"] for w in hosts.values()}) == 2  # spread over both nodes
        t_kill = time.monotonic()
        os.kill(hosts[ids[0]]["pid"], signal.SIGKILL)
        _answers_from_elsewhere(api.url, ids[0], {hosts[ids[0]]["pid"]})
        print(f"map answering again {time.monotonic() - t_kill:.2f} s after the kill")

        lose_node.wait(timeout=300)  # (b) the second node lost while the clients post
        hosts = {w["map"]: w for w in httpx.get(api.url + "/v1/workers").json()["workers"]}
        t_kill = time.monotonic()
        gone = set(ray_cluster.stop_node(1, hard=True))
        hit = [m for m in ids if hosts[m]["pid"] in gone]
        assert hit  # some maps were on the second node
        for m in hit:
            _answers_from_elsewhere(api.url, m, gone)
        print(f"{len(hit)} maps answering again {time.monotonic() - t_kill:.2f} s after")

        for t in clients:
            t.join(timeout=300)
            assert not t.is_alive()
        for map_id, out in zip(ids, acked, strict=True):
            figures = check_log(api.url, map_id, FRAMES, out)
            assert figures["lost"] == figures["duplicated"] == 0, figures
            assert figures["answer_changed_on_retry"] == 0, figures
        untouched = [m for m in ids[1:] if m not in hit]
        with httpx.Client(base_url=api.url, timeout=120) as c:
            # the maps no fault hit computed the same (they had the same frames)
            trajectories = [_trajectory(c, m) for m in untouched]
            assert all(t == trajectories[0] for t in trajectories[1:])
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
