"""CPU per frame of the request path: the API process, the workers, and the in-process
pipeline for the same frames.

CPU time (from /proc), not wall time: the machine is shared, and a process's CPU per
frame is much steadier than its throughput. Run from the repository root, niced::

    nice -n 10 python -m bench.request_cpu [--maps 8] [--clients 4] [--frames 150]
                                           [--profile DIR] [--out bench/results]

A ``covslam serve --workers 2`` (SQLite, the default settings) gets `maps` maps (the
load bench's config: landmark cap 50) and `clients` clients per map post their
simulated frames (the load bench's frames, one keep-alive connection per client,
closed loop). Then the same frames go through ``MapSession.submit`` in one process.
Reported per frame, ms: the API process, the workers, the in-process sessions, and the
request path's cost outside the estimator: ``workers - in_process + api``.

``--profile DIR``: the API process and each worker run under cProfile (CPU time);
their stats go to ``DIR/api.prof`` and ``DIR/worker<i>.prof`` (read with pstats;
the profiler's own overhead inflates the CPU figures of that run).

Writes ``<out>/request_cpu.json``.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

from bench.load import MAP_CONFIG, Server, cpu_bound, make_frames, post_all

PROFILE_ENV = "COVSLAM_BENCH_PROFILE_DIR"


def _times(pid: int) -> dict[str, float]:
    """CPU seconds (user, system) and context switches (voluntary, involuntary) a process
    has had so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    tick = os.sysconf("SC_CLK_TCK")
    out = {"user": int(fields[11]) / tick, "system": int(fields[12]) / tick}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(("voluntary_ctxt_switches", "nonvoluntary_ctxt_switches")):
            name, value = line.split(":")
            out[name.split("_")[0]] = float(value)
    return out


def _server_times(server: Server, client: httpx.Client) -> dict[str, dict[str, float]]:
    """`_times` of the API process and of the workers (summed)."""
    assert server.proc is not None
    pids = [w["pid"] for w in client.get("/v1/workers").json()["workers"]]
    workers: dict[str, float] = {}
    for pid in pids:
        for name, value in _times(pid).items():
            workers[name] = workers.get(name, 0.0) + value
    return {"api": _times(server.proc.pid), "workers": workers}


def profiled_worker(conn: Any, settings: dict[str, Any], index: int) -> None:
    """`service.worker.serve` under cProfile (CPU time); stats to $PROFILE_ENV."""
    from service import worker

    profile = cProfile.Profile(time.process_time)
    profile.enable()
    try:
        worker.serve(conn, settings, index)
    finally:
        profile.disable()
        profile.dump_stats(str(Path(os.environ[PROFILE_ENV]) / f"worker{index}.prof"))


def _exit(signum: int, frame: Any) -> None:
    raise SystemExit(0)


def serve_profiled(argv: list[str]) -> None:
    """`covslam serve argv` under cProfile, its workers too (see `profiled_worker`)."""
    import types

    from api import cli
    from service import pool

    pool.worker = types.SimpleNamespace(serve=profiled_worker)  # type: ignore[assignment]
    profile = cProfile.Profile(time.process_time)
    profile.enable()
    try:
        # uvicorn raises a SIGTERM again after its shutdown: end by SystemExit instead
        signal.signal(signal.SIGTERM, _exit)
        cli.main(["serve", *argv])
    finally:
        profile.disable()
        profile.dump_stats(str(Path(os.environ[PROFILE_ENV]) / "api.prof"))


class ProfiledServer(Server):
    def __init__(self, data: Path, log: Path, profile: Path) -> None:
        super().__init__(data, log)
        self.profile = profile

    def start(self) -> float:
        env = {**os.environ, "COVSLAM_LOG_LEVEL": "warning", PROFILE_ENV: str(self.profile)}
        t0 = time.monotonic()
        with self.log.open("ab") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "bench.request_cpu", "--serve-profiled", "--port",
                 str(self.port), "--data-dir", str(self.data), "--workers", "2"],
                env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
            )  # fmt: skip
        while time.monotonic() - t0 < 120:
            if self.proc.poll() is not None:
                raise RuntimeError(self.log.read_text()[-2000:])
            try:
                if httpx.get(self.url + "/readyz", timeout=1).status_code == 200:
                    return time.monotonic() - t0
            except httpx.TransportError:
                pass
            time.sleep(0.02)
        raise TimeoutError(self.log.read_text()[-2000:])


def run(args: argparse.Namespace) -> dict[str, Any]:
    frames = make_frames(args.maps, args.clients, args.frames)
    work = Path(tempfile.mkdtemp(prefix="covslam-cpu-"))
    if args.profile is not None:
        args.profile.mkdir(parents=True, exist_ok=True)
        server: Server = ProfiledServer(work / "data", work / "server.log", args.profile.resolve())
    else:
        server = Server(work / "data", work / "server.log")
    server.start()
    try:
        client = httpx.Client(base_url=server.url, timeout=120)
        maps = [
            client.post("/v1/maps", json={"name": f"m{i}", "config": MAP_CONFIG}).json()["id"]
            for i in range(args.maps)
        ]
        cpu0 = _server_times(server, client)
        http_run, posted = post_all(server.port, maps, frames, limit_s=600)
        cpu1 = _server_times(server, client)
        client.close()
        server.stop()
    finally:
        server.kill()
    done = [
        [run[:n] for run, n in zip(runs, ns, strict=True)]
        for runs, ns in zip(frames, posted, strict=True)
    ]
    bound = cpu_bound(done, cores=1)
    n = http_run["frames"]
    per_frame = {
        who: {k: round((1e3 if k in ("user", "system") else 1) * (v - cpu0[who][k]) / n, 3)
              for k, v in cpu1[who].items()}
        for who in ("api", "workers")
    }  # fmt: skip
    api = per_frame["api"]["user"] + per_frame["api"]["system"]
    workers = per_frame["workers"]["user"] + per_frame["workers"]["system"]
    in_process = bound["cpu_ms_per_frame"]
    return {
        "command": "nice -n 10 python -m bench.request_cpu " + " ".join(sys.argv[1:]),
        "maps": args.maps,
        "clients_per_map": args.clients,
        "frames": n,
        "profiled": args.profile is not None,
        "http_frames_per_s": http_run["frames_per_s"],
        "loadavg": http_run["loadavg"],
        "cpu_ms_per_frame": {
            "api_process": round(api, 3),
            "workers": round(workers, 3),
            "in_process": in_process,
            "worker_excess": round(workers - in_process, 3),
            "outside_estimator": round(workers - in_process + api, 3),
        },
        "per_frame": per_frame,
    }


def main() -> None:
    if sys.argv[1:2] == ["--serve-profiled"]:
        serve_profiled(sys.argv[2:])
        return
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--maps", type=int, default=8)
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--frames", type=int, default=150, help="per client")
    parser.add_argument("--profile", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    args = parser.parse_args()
    result = run(args)
    print(json.dumps(result, indent=2), flush=True)
    if args.profile is None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "request_cpu.json").write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
