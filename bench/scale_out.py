"""Scale-out: one MRCLAM-6 replay through three deployments, and a failover on Ray.

1. Identity: ``covslam replay mrclam DIR --robot R --url URL --trajectory T.tum``
   against ``covslam serve`` with local/SQLite, local/PostgreSQL and ray/PostgreSQL; the
   three TUM files must be byte-identical (their sha256 is reported).
2. Failover: ray/PostgreSQL on a local two-node Ray cluster (``ray start``, one CPU per
   node). M maps, one client per map posting the first F frames of MRCLAM robot 1..M
   (``service.offline.http_client.replay_http``: it retries on 503 and transport errors, as any
   client should). Once map 0 has K acknowledged frames, the process hosting its actor
   is killed with SIGKILL; the time until map 0 answers again is measured with GET
   /pose polled every 20 ms. Afterwards, for every map: the frame log holds exactly the
   frames posted (0 duplicated), and re-posting every frame is answered from the log
   with the acknowledged result byte for byte (0 lost).

PostgreSQL is a private server (``initdb`` + ``pg_ctl``, fsync on) in a temporary
directory; the Ray nodes and the servers are stopped by their process ids afterwards.
Writes ``<out>/scale_out.json``::

    python -m bench.scale_out [--robot 1] [--maps 3] [--frames 300] [--kill-after 100]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from bench.clusters import LocalRayCluster, PrivatePostgres, Service
from graph.types import FrameInput
from service.frames_io import frame_to_dict
from service.offline.datasets.mrclam import default_mrclam_dir, load_mrclam, mrclam_frames
from service.offline.http_client import HttpReplay, replay_http

MAP_CONFIG = {"landmark_cap": 8, "policy": "coverage"}


def _identity(name: str, args: list[str], robot: int, data: Path, work: Path) -> dict[str, Any]:
    """Replay one robot through a fresh service; the TUM file's digest and timings."""
    stem = name.replace("/", "_")
    service = Service(work / f"{stem}.log", *args)
    try:
        ready_s = service.wait_ready()
        tum, stats = work / f"{stem}.tum", work / f"{stem}.json"
        t0 = time.monotonic()
        subprocess.run(
            [sys.executable, "-m", "api.cli", "replay", "mrclam", str(data),
             "--robot", str(robot), "--url", service.url, "--trajectory", str(tum),
             "--stats", str(stats)],
            check=True, capture_output=True, text=True,
        )  # fmt: skip
        wall = time.monotonic() - t0
    finally:
        service.stop()
    text = tum.read_bytes()
    latency = json.loads(stats.read_text())["latency_ms"]
    return {
        "deployment": name,
        "serve_args": args,
        "ready_s": round(ready_s, 2),
        "replay_wall_s": round(wall, 1),
        "frames": len(latency),
        "trajectory_rows": text.count(b"\n"),
        "trajectory_sha256": hashlib.sha256(text).hexdigest(),
    }


def _status(url: str) -> list[dict[str, Any]]:
    workers: list[dict[str, Any]] = httpx.get(url + "/v1/workers", timeout=10).json()["workers"]
    return workers


def _wait_acked(url: str, map_id: str, count: int, timeout_s: float = 600.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        r = httpx.get(f"{url}/v1/maps/{map_id}", timeout=30)
        if r.status_code == 200 and r.json()["counts"]["frames"] >= count:
            return
        time.sleep(0.2)
    raise TimeoutError(f"map {map_id}: {count} frames not reached")


def _until_answers(url: str, map_id: str, since: float) -> float:
    """Seconds from `since` until GET /pose of the map answers 200."""
    with httpx.Client(base_url=url, timeout=120) as c:
        while True:
            try:
                if c.get(f"/v1/maps/{map_id}/pose").status_code == 200:
                    return time.monotonic() - since
            except httpx.TransportError:
                pass
            time.sleep(0.02)


def post_until_answered(client: httpx.Client, map_id: str, frame: dict[str, Any]) -> dict:
    """Post a frame, retrying on 503 (after Retry-After) and transport errors, until the
    service answers; its result (any other status raises)."""
    while True:
        try:
            r = client.post(f"/v1/maps/{map_id}/frames", json=frame)
        except httpx.TransportError:
            time.sleep(0.2)
            continue
        if r.status_code == 503:
            time.sleep(float(r.headers.get("retry-after", "1")))
            continue
        if r.status_code != 200:
            raise RuntimeError(f"map {map_id} seq {frame['seq']}: {r.status_code} {r.text}")
        result: dict[str, Any] = r.json()
        return result


def scale(url: str, data: Path, *, maps: int, clients: int, frames: int) -> dict[str, Any]:
    """`maps` maps (MRCLAM robots 1-5 in turn, the first `frames` frames each), `clients`
    threads each posting to its share of the maps, frame by frame in turn; throughput and
    per-frame round trips."""
    runs = []
    for i in range(maps):
        mine, _ = mrclam_frames(load_mrclam(data, i % 5 + 1))
        runs.append([frame_to_dict(f) for f in mine[:frames]])
    with httpx.Client(base_url=url, timeout=120) as c:
        ids = []
        for i in range(maps):
            r = c.post("/v1/maps", json={"name": f"scale{i}", "config": MAP_CONFIG})
            r.raise_for_status()
            ids.append(r.json()["id"])
    latency: list[float] = []

    def client(k: int) -> None:
        mine = list(range(k, maps, clients))
        with httpx.Client(base_url=url, timeout=300) as c:
            for j in range(frames):
                for m in mine:
                    t0 = time.perf_counter()
                    post_until_answered(c, ids[m], runs[m][j])
                    latency.append(1e3 * (time.perf_counter() - t0))

    threads = [threading.Thread(target=client, args=(k,)) for k in range(clients)]
    t0 = time.monotonic()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.monotonic() - t0
    ms = np.asarray(latency)
    nodes = {w.get("node") for w in _status(url) if w.get("map") in ids}
    return {
        "maps": maps,
        "clients": clients,
        "frames": int(ms.size),
        "wall_s": round(wall, 1),
        "frames_per_s": round(ms.size / wall, 1),
        "latency_ms_p50": round(float(np.percentile(ms, 50)), 1),
        "latency_ms_p99": round(float(np.percentile(ms, 99)), 1),
        "nodes_used": len(nodes - {None}),
    }


def check_log(url: str, map_id: str, frames: list[dict[str, Any]], acked: list[dict]) -> dict:
    """Lost and duplicated frames of a map: re-post every frame (each must be answered
    from the log with its acknowledged result) and count the log's frames."""
    lost = changed = 0
    with httpx.Client(base_url=url, timeout=120) as c:
        for frame, result in zip(frames, acked, strict=True):
            r = c.post(f"/v1/maps/{map_id}/frames", json=frame)
            if r.headers.get("idempotent-replayed") != "true":
                lost += 1
            elif r.json() != result:
                changed += 1
        logged = c.get(f"/v1/maps/{map_id}").json()["counts"]["frames"]
    return {
        "posted": len(frames),
        "acknowledged": len(acked),
        "logged": logged,
        "lost": lost,
        "duplicated": logged - len(frames),
        "answer_changed_on_retry": changed,
    }


def failover(url: str, data: Path, *, maps: int, frames: int, kill_after: int) -> dict[str, Any]:
    runs: list[list[FrameInput]] = []
    for robot in range(1, maps + 1):
        mine, _ = mrclam_frames(load_mrclam(data, robot))
        runs.append(mine[:frames])
    ids = []
    with httpx.Client(base_url=url, timeout=120) as c:
        for i in range(maps):
            r = c.post("/v1/maps", json={"name": f"robot{i + 1}", "config": MAP_CONFIG})
            r.raise_for_status()
            ids.append(r.json()["id"])
    replays: list[HttpReplay | None] = [None] * maps

    def client(i: int) -> None:
        replays[i] = replay_http(runs[i], url=url, map_id=ids[i], progress=False)

    threads = [threading.Thread(target=client, args=(i,)) for i in range(maps)]
    for t in threads:
        t.start()
    _wait_acked(url, ids[0], kill_after)
    before = {w["map"]: w for w in _status(url)}
    victim = before[ids[0]]
    t_kill = time.monotonic()
    os.kill(int(victim["pid"]), signal.SIGKILL)
    answers_s = _until_answers(url, ids[0], t_kill)
    for t in threads:
        t.join()
    after = {w["map"]: w for w in _status(url)}
    checks = []
    for i, replay in enumerate(replays):
        assert replay is not None
        checks.append(
            {
                "map": ids[i],
                "killed": i == 0,
                "retries": replay.retries,
                "max_latency_ms": round(max(replay.latency_ms), 1),
                **check_log(url, ids[i], [frame_to_dict(f) for f in runs[i]], replay.results),
            }
        )
    return {
        "maps": maps,
        "frames_per_map": frames,
        "killed_after_frames": kill_after,
        "nodes_before": {m: w["node"] for m, w in before.items()},
        "nodes_after": {m: w["node"] for m, w in after.items()},
        "killed_pid": victim["pid"],
        "restarted_pid": after[ids[0]]["pid"],
        "seconds_until_map_answers_again": round(answers_s, 2),
        "per_map": checks,
        "lost_total": sum(c["lost"] for c in checks),
        "duplicated_total": sum(c["duplicated"] for c in checks),
    }


def _scale_runs(
    args: argparse.Namespace, data: Path, work: Path, pg: PrivatePostgres, two: LocalRayCluster
) -> list[dict[str, Any]]:
    """The scale run on the two-node cluster, on a one-node cluster (started for it), and
    with the local engine (two worker processes, and one per map), each on a fresh
    database."""
    out: list[dict[str, Any]] = []
    one = LocalRayCluster(nodes=1, cpus=1).start()
    try:
        deployments = [
            ("ray/postgresql, 2 nodes", ["--engine", "ray", "--ray-address", two.address]),
            ("ray/postgresql, 1 node", ["--engine", "ray", "--ray-address", one.address]),
            ("local/postgresql, 2 workers", ["--workers", "2"]),
            (f"local/postgresql, {args.scale_maps} workers", ["--workers", str(args.scale_maps)]),
        ]
        for name, serve_args in deployments:
            full = [*serve_args, "--store-url", pg.new_database()]
            service = Service(work / f"scale{len(out)}.log", *full)
            try:
                service.wait_ready()
                run = scale(
                    service.url, data, maps=args.scale_maps, clients=args.scale_clients,
                    frames=args.scale_frames,
                )  # fmt: skip
            finally:
                service.stop()
            out.append({"deployment": name, **run})
            print(json.dumps(out[-1]), flush=True)
    finally:
        one.stop()
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=None, help="MRCLAM-6 folder")
    ap.add_argument("--robot", type=int, default=1, help="robot replayed for the identity check")
    ap.add_argument("--maps", type=int, default=3, help="maps in the failover run")
    ap.add_argument("--frames", type=int, default=300, help="frames per map in the failover run")
    ap.add_argument("--kill-after", type=int, default=100, help="map 0's frames before the kill")
    ap.add_argument("--skip-identity", action="store_true")
    ap.add_argument("--skip-failover", action="store_true")
    ap.add_argument(
        "--scale-frames", type=int, default=0, help="frames per map of the scale run (0: none)"
    )
    ap.add_argument("--scale-maps", type=int, default=8)
    ap.add_argument("--scale-clients", type=int, default=4)
    ap.add_argument("--out", type=Path, default=Path("bench/results"))
    args = ap.parse_args(argv)
    data = args.data or default_mrclam_dir()
    report: dict[str, Any] = {"host_cpus": os.cpu_count(), "map_config": MAP_CONFIG}
    pg = PrivatePostgres(fsync=True).start()
    ray_cluster: LocalRayCluster | None = None
    try:
        ray_cluster = LocalRayCluster(nodes=2, cpus=1).start()
        ray_args = ["--engine", "ray", "--ray-address", ray_cluster.address]
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            if not args.skip_identity:
                runs = [
                    ("local/sqlite", ["--data-dir", str(work / "sqlite"), "--workers", "1"]),
                    ("local/postgresql", ["--store-url", pg.new_database(), "--workers", "1"]),
                    ("ray/postgresql", [*ray_args, "--store-url", pg.new_database()]),
                ]
                report["identity"] = [
                    _identity(name, a, args.robot, data, work) for name, a in runs
                ]
                digests = {r["trajectory_sha256"] for r in report["identity"]}
                report["identical_trajectories"] = len(digests) == 1
                print(json.dumps(report["identity"], indent=1), flush=True)
            if not args.skip_failover:
                service = Service(
                    work / "failover.log", *ray_args, "--store-url", pg.new_database()
                )
                try:
                    service.wait_ready()
                    report["failover"] = failover(
                        service.url, data, maps=args.maps, frames=args.frames,
                        kill_after=args.kill_after,
                    )  # fmt: skip
                finally:
                    service.stop()
            if args.scale_frames:
                report["scale"] = _scale_runs(args, data, work, pg, ray_cluster)
    finally:
        if ray_cluster is not None:
            ray_cluster.stop()
        pg.stop()
    args.out.mkdir(parents=True, exist_ok=True)
    name = "scale_out.json" if not args.skip_failover else "scale_out_throughput.json"
    (args.out / name).write_text(json.dumps(report, indent=1) + "\n")
    print(json.dumps(report.get("failover"), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
