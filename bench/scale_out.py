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

from graph.types import FrameInput
from service.frames_io import frame_to_dict
from service.offline.datasets.mrclam import default_mrclam_dir, load_mrclam, mrclam_frames
from service.offline.http_client import HttpReplay, check_log, post_until_answered, replay_http
from tests.support.clusters import LocalRayCluster, PrivatePostgres, Service

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


def _until_answers(url: str, map_id: str, since: float, gone: set[int]) -> float:
    """Seconds from `since` until the map answers GET /pose (polled every 20 ms) from a
    process other than those in `gone` (a dying one may still answer for a moment)."""
    first_new: float | None = None
    with httpx.Client(base_url=url, timeout=120) as c:
        while True:
            try:
                ok = c.get(f"/v1/maps/{map_id}/pose").status_code == 200
            except httpx.TransportError:
                ok = False
            if ok:
                t = time.monotonic()
                pid = {w["map"]: w["pid"] for w in _status(url)}.get(map_id)
                if pid in gone:
                    first_new = None
                else:
                    first_new = first_new or t
                    if pid is not None:
                        return first_new - since
            time.sleep(0.02)


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


FAULTS = ("worker", "node-stop", "node-loss")
"""What fails over: the process hosting map 0's actor (SIGKILL); the second node
stopped as ``ray stop`` does (SIGTERM to each of its processes); the second node lost
(SIGKILL to each of its processes at once, as when its machine fails)."""


def _inject(fault: str, cluster: LocalRayCluster, victim: dict[str, Any]) -> None:
    """Make `fault` happen (returns once its processes ended)."""
    if fault == "worker":
        os.kill(int(victim["pid"]), signal.SIGKILL)
    else:
        cluster.stop_node(1, hard=fault == "node-loss")


def failover(
    url: str,
    data: Path,
    cluster: LocalRayCluster,
    *,
    fault: str,
    maps: int,
    frames: int,
    kill_after: int,
) -> dict[str, Any]:
    """`maps` maps (MRCLAM robots 1.., the first `frames` frames each), one client each;
    `fault` once map 0 has `kill_after` frames. Per map: lost, duplicated, retries, and
    for each map the fault hit, the seconds until it answered again."""
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
    second = set(cluster.node_pids(1))
    gone = {int(before[ids[0]]["pid"])} if fault == "worker" else second
    hit = [m for m in ids if before[m]["pid"] in gone]
    answers: dict[str, float] = {}
    t_kill = time.monotonic()

    def watch(map_id: str) -> None:
        answers[map_id] = _until_answers(url, map_id, t_kill, gone)

    watchers = [threading.Thread(target=watch, args=(m,)) for m in hit]
    for t in watchers:
        t.start()
    _inject(fault, cluster, before[ids[0]])
    for t in [*watchers, *threads]:
        t.join()
    after = {w["map"]: w for w in _status(url)}
    checks = []
    for i, replay in enumerate(replays):
        assert replay is not None
        checks.append(
            {
                "map": ids[i],
                "hit": ids[i] in hit,
                "node_before": "second" if before[ids[i]]["pid"] in second else "head",
                "seconds_until_answers_again": round(answers[ids[i]], 2)
                if ids[i] in answers
                else None,
                "retries": replay.retries,
                "max_latency_ms": round(max(replay.latency_ms), 1),
                **check_log(url, ids[i], [frame_to_dict(f) for f in runs[i]], replay.results),
            }
        )
    return {
        "fault": fault,
        "maps": maps,
        "clients": maps,
        "frames_per_map": frames,
        "fault_after_frames_of_map_0": kill_after,
        "maps_hit": len(hit),
        "ended_pids": sorted(gone),
        "moved_to_new_process": sum(after[m]["pid"] not in gone for m in hit),
        "seconds_until_map_answers_again": {m: round(s, 2) for m, s in answers.items()},
        "per_map": checks,
        "lost_total": sum(c["lost"] for c in checks),
        "duplicated_total": sum(c["duplicated"] for c in checks),
        "answer_changed_total": sum(c["answer_changed_on_retry"] for c in checks),
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


def _percentiles(ms: list[float]) -> dict[str, float]:
    return {
        "p50": round(float(np.percentile(ms, 50)), 2),
        "p99": round(float(np.percentile(ms, 99)), 2),
    }


def _worker_ms(result: dict[str, Any]) -> float:
    """The worker's own time for a frame: its stages (total) and the durable log append."""
    timing = result["timing_ms"]
    return float(timing.get("total", 0.0)) + float(timing.get("log", 0.0))


def added_latency(urls: dict[str, str], data: Path, *, frames: int, warmup: int = 10) -> dict:
    """One client, one map per deployment with the same config, the same frames (the
    first `frames` of MRCLAM robot 1: a few bearings each, a small graph) posted to both
    in turn (which goes first alternates), each followed by GET /pose (no estimator
    work): per deployment the round trips, the worker's own time per frame and the
    round trip less that; the paired difference of each to the first deployment's; all
    after `warmup` frames. The answers must be the same but for their timings."""
    mine, _ = mrclam_frames(load_mrclam(data, 1))
    posts = [frame_to_dict(f) for f in mine[:frames]]
    names = list(urls)
    clients = {k: httpx.Client(base_url=u, timeout=120) for k, u in urls.items()}
    table: dict[str, dict[str, list[float]]] = {
        what: {k: [] for k in names}
        for what in ("post_frame_ms", "worker_ms", "post_frame_less_worker_ms", "get_pose_ms")
    }
    same = True
    try:
        ids = {}
        for k, c in clients.items():
            r = c.post("/v1/maps", json={"name": "latency", "config": MAP_CONFIG})
            r.raise_for_status()
            ids[k] = r.json()["id"]
        for j, frame in enumerate(posts):
            order = names if j % 2 == 0 else names[::-1]
            answers = {}
            for k in order:
                t0 = time.perf_counter()
                r = clients[k].post(f"/v1/maps/{ids[k]}/frames", json=frame)
                rt = 1e3 * (time.perf_counter() - t0)
                r.raise_for_status()
                answers[k] = r.json()
                table["post_frame_ms"][k].append(rt)
                table["worker_ms"][k].append(_worker_ms(answers[k]))
                table["post_frame_less_worker_ms"][k].append(rt - _worker_ms(answers[k]))
                del answers[k]["timing_ms"]
            same = same and all(a == answers[names[0]] for a in answers.values())
            for k in order:
                t0 = time.perf_counter()
                r = clients[k].get(f"/v1/maps/{ids[k]}/pose")
                table["get_pose_ms"][k].append(1e3 * (time.perf_counter() - t0))
                r.raise_for_status()
    finally:
        for c in clients.values():
            c.close()
    out: dict[str, Any] = {"frames": frames, "warmup_frames_left_out": warmup}
    out["identical_answers_but_timings"] = same
    for what, series in table.items():
        kept = {k: v[warmup:] for k, v in series.items()}
        out[what] = {k: _percentiles(v) for k, v in kept.items()}
        for k in names[1:]:
            diff = [a - b for a, b in zip(kept[k], kept[names[0]], strict=True)]
            out[what][f"{k} - {names[0]}, paired"] = _percentiles(diff)
    return out


def _latency_run(
    work: Path, data: Path, pg: PrivatePostgres, ray_args: list[str], *, frames: int
) -> dict[str, Any]:
    """`added_latency` of local/PostgreSQL (one worker) against ray/PostgreSQL, both
    serving at once on one PostgreSQL server (a database each)."""
    local = Service(work / "latency-local.log", "--workers", "1", "--store-url",
                    pg.new_database())  # fmt: skip
    ray_service = Service(work / "latency-ray.log", *ray_args, "--store-url", pg.new_database())
    try:
        local.wait_ready()
        ray_service.wait_ready()
        urls = {"local": local.url, "ray": ray_service.url}
        return added_latency(urls, data, frames=frames)
    finally:
        ray_service.stop()
        local.stop()


def _with_service(
    work: Path, name: str, serve_args: list[str], run: Any, env: dict[str, str] | None = None
) -> Any:
    """`run(url)` against a fresh `covslam serve` with `serve_args`, stopped afterwards."""
    service = Service(work / f"{name}.log", *serve_args, env=env)
    try:
        service.wait_ready()
        return run(service.url)
    finally:
        service.stop()


def _failovers(
    args: argparse.Namespace, data: Path, work: Path, pg: PrivatePostgres, two: LocalRayCluster
) -> list[dict[str, Any]]:
    """One failover run per fault, each on a fresh database; a node fault on a two-node
    cluster of its own (it ends the second node)."""
    out = []
    for fault in args.faults:
        cluster = two if fault == "worker" else LocalRayCluster(nodes=2, cpus=1).start()
        try:
            serve = ["--engine", "ray", "--ray-address", cluster.address]
            serve += ["--store-url", pg.new_database()]

            def run(url: str, c: LocalRayCluster = cluster, f: str = fault) -> dict[str, Any]:
                return failover(url, data, c, fault=f, maps=args.maps, frames=args.frames,
                                kill_after=args.kill_after)  # fmt: skip

            env = {"COVSLAM_RAY__ACTOR_CPUS": str(args.actor_cpus)}
            out.append({"actor_cpus": args.actor_cpus,
                        **_with_service(work, f"failover-{fault}", serve, run, env)})  # fmt: skip
        finally:
            if cluster is not two:
                cluster.stop()
        print(json.dumps({k: v for k, v in out[-1].items() if k != "per_map"}), flush=True)
    return out


def _merge(path: Path, report: dict[str, Any]) -> None:
    """Write `report` into the JSON file at `path`, keeping the sections not run now."""
    old = json.loads(path.read_text()) if path.exists() else {}
    path.write_text(json.dumps({**old, **report}, indent=1) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=None, help="MRCLAM-6 folder")
    ap.add_argument("--robot", type=int, default=1, help="robot replayed for the identity check")
    ap.add_argument("--maps", type=int, default=4, help="maps (and clients) in a failover run")
    ap.add_argument("--frames", type=int, default=300, help="frames per map in the failover run")
    ap.add_argument("--kill-after", type=int, default=100, help="map 0's frames before the fault")
    ap.add_argument(
        "--faults", type=lambda v: v.split(","), default=list(FAULTS),
        help=f"comma-separated, of {', '.join(FAULTS)}",
    )  # fmt: skip
    ap.add_argument(
        "--actor-cpus", type=float, default=0.25,
        help="COVSLAM_RAY__ACTOR_CPUS of the failover runs (Ray spreads actors that "
        "reserve CPUs round-robin over the nodes, actors of 0 CPUs at random)",
    )  # fmt: skip
    ap.add_argument("--skip-identity", action="store_true")
    ap.add_argument("--skip-failover", action="store_true")
    ap.add_argument(
        "--latency-frames", type=int, default=0,
        help="frames of the added-latency run, ray against local (0: none)",
    )  # fmt: skip
    ap.add_argument(
        "--scale-frames", type=int, default=0, help="frames per map of the scale run (0: none)"
    )
    ap.add_argument("--scale-maps", type=int, default=8)
    ap.add_argument("--scale-clients", type=int, default=4)
    ap.add_argument("--out", type=Path, default=Path("bench/results"))
    args = ap.parse_args(argv)
    if unknown := set(args.faults) - set(FAULTS):
        ap.error(f"unknown faults {sorted(unknown)}")
    data = args.data or default_mrclam_dir()
    report: dict[str, Any] = {"host_cpus": os.cpu_count(), "map_config": MAP_CONFIG}
    throughput: dict[str, Any] = {}
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
            if args.latency_frames:
                report["added_latency"] = _latency_run(
                    work, data, pg, ray_args, frames=args.latency_frames
                )
                print(json.dumps(report["added_latency"], indent=1), flush=True)
            if not args.skip_failover:
                report["failover"] = _failovers(args, data, work, pg, ray_cluster)
            if args.scale_frames:
                throughput["scale"] = _scale_runs(args, data, work, pg, ray_cluster)
    finally:
        if ray_cluster is not None:
            ray_cluster.stop()
        pg.stop()
    args.out.mkdir(parents=True, exist_ok=True)
    _merge(args.out / "scale_out.json", report)
    if throughput:
        base = {k: report[k] for k in ("host_cpus", "map_config")}
        _merge(args.out / "scale_out_throughput.json", {**base, **throughput})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
