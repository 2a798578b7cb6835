"""CPU per frame of the request path: the API process, the workers, and the in-process
pipeline for the same frames.

CPU time (from /proc), not wall time: the machine is shared, and a process's CPU per
frame is much steadier than its throughput. Run from the repository root, niced::

    nice -n 10 python -m bench.request_cpu [--maps 8] [--clients 4] [--frames 150]
                                           [--profile DIR | --versus DIR]
                                           [--out bench/results]

A ``covslam serve --workers 2`` (SQLite, the default settings) gets `maps` maps (the
load bench's config: landmark cap 50) and `clients` clients per map post their
simulated frames (the load bench's frames, one keep-alive connection per client,
closed loop). Then the same frames go through ``MapSession.submit`` in one process.
Reported per frame, ms: the API process, the workers, the in-process sessions, and the
request path's cost outside the estimator: ``workers - in_process + api``.

``--versus DIR``: a server of this tree and one of the checkout DIR (e.g. ``git worktree
add DIR <commit>``) side by side, the same frames posted to both at the same time
(`maps` maps and `clients` clients each): the CPU per frame of each one's API process
and workers, paired in time, so that the machine's load moves both alike (printed, not
written).

``--profile DIR``: the API process and each worker sample their own stacks every
0.5 ms of CPU time (SIGPROF; a deterministic profiler's per-call overhead would
inflate exactly the many small Python calls this looks for); the samples go to
``DIR/api.samples`` and ``DIR/worker<i>.samples``, and ``python -m bench.request_cpu
--report DIR`` prints each function's share (self and with its callees).

Writes ``<out>/request_cpu.json``.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import pickle
import signal
import sys
import tempfile
import threading
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


Stack = tuple[str, ...]


class Sampler:
    """The main thread's stacks every `interval_s` of the process's CPU time (ITIMER_PROF:
    waiting is not sampled), each weighted with the CPU seconds since the sample before
    it: Python runs a signal handler only between two bytecodes, so the timer's signals
    during a long C call (GTSAM, the event loop) come as one, charged to the Python
    function that runs next (the caller of a C function; the callback the event loop
    runs after its own work)."""

    def __init__(self, interval_s: float = 0.0005) -> None:
        self.interval_s = interval_s
        self.counts: dict[Stack, float] = collections.defaultdict(float)
        self._last = 0.0

    def _sample(self, signum: int, frame: Any) -> None:
        now = time.process_time()
        stack = []
        while frame is not None:
            code = frame.f_code
            stack.append(f"{code.co_filename}:{code.co_firstlineno}({code.co_name})")
            frame = frame.f_back
        self.counts[tuple(stack)] += now - self._last
        self._last = now

    def start(self) -> None:
        self._last = time.process_time()
        signal.signal(signal.SIGPROF, self._sample)
        signal.setitimer(signal.ITIMER_PROF, self.interval_s, self.interval_s)

    def stop(self, path: Path) -> None:
        signal.setitimer(signal.ITIMER_PROF, 0, 0)
        path.write_bytes(pickle.dumps(dict(self.counts)))


def profiled_worker(conn: Any, settings: dict[str, Any], index: int) -> None:
    """`service.worker.serve`, sampled (see `Sampler`); samples to $PROFILE_ENV."""
    from service import worker

    sampler = Sampler()
    sampler.start()
    try:
        worker.serve(conn, settings, index)
    finally:
        sampler.stop(Path(os.environ[PROFILE_ENV]) / f"worker{index}.samples")


def _exit(signum: int, frame: Any) -> None:
    raise SystemExit(0)


def serve_profiled(argv: list[str]) -> None:
    """`covslam serve argv`, sampled, its workers too (see `profiled_worker`)."""
    import types

    from api import cli
    from service import pool

    pool.worker = types.SimpleNamespace(serve=profiled_worker)  # type: ignore[assignment]
    sampler = Sampler()
    sampler.start()
    try:
        # uvicorn raises a SIGTERM again after its shutdown: end by SystemExit instead
        signal.signal(signal.SIGTERM, _exit)
        cli.main(["serve", *argv])
    finally:
        sampler.stop(Path(os.environ[PROFILE_ENV]) / "api.samples")


def report(folder: Path, top: int = 40) -> None:
    """Each function's share of the sampled CPU time of each process kind (self: the
    function was running; total: it was on the stack), %."""
    for kind in ("api", "worker"):
        counts: dict[Stack, float] = collections.defaultdict(float)
        for path in sorted(folder.glob(f"{kind}*.samples")):
            for stack, seconds in pickle.loads(path.read_bytes()).items():
                counts[stack] += seconds
        n = sum(counts.values())
        own: dict[str, float] = collections.defaultdict(float)
        total: dict[str, float] = collections.defaultdict(float)
        for stack, c in counts.items():
            own[stack[0]] += c
            for name in set(stack):
                total[name] += c
        print(f"== {kind}: {n:.2f} CPU s sampled")
        for title, table in (("self", own), ("total", total)):
            print(f"-- {title}")
            for name, c in sorted(table.items(), key=lambda item: -item[1])[:top]:
                print(f"{100 * c / n:6.2f} %  {name.replace(os.getcwd() + '/', '')}")


class ProfiledServer(Server):
    def __init__(self, data: Path, log: Path, profile: Path) -> None:
        super().__init__(data, log)
        self.profile = profile

    def start(self) -> float:
        env = {**os.environ, "COVSLAM_LOG_LEVEL": "warning", PROFILE_ENV: str(self.profile)}
        return self.launch(["-m", "bench.request_cpu", "--serve-profiled"], env)


class TreeServer(Server):
    """`covslam serve --workers 2` from the source tree `tree` (another checkout)."""

    def __init__(self, data: Path, log: Path, tree: Path) -> None:
        super().__init__(data, log)
        self.tree = tree

    def start(self) -> float:
        env = {**os.environ, "COVSLAM_LOG_LEVEL": "warning"}
        env.pop("PYTHONPATH", None)
        return self.launch(["-m", "api.cli", "serve"], env, cwd=self.tree)


def versus(args: argparse.Namespace) -> dict[str, Any]:
    """This tree's server and `args.versus`'s side by side, the same frames posted to both
    at the same time (each gets `maps` maps, `clients` clients each): a change's effect
    on the CPU per frame of each process, paired in time (the machine's load swings
    move both alike)."""
    frames = make_frames(args.maps, args.clients, args.frames)
    work = Path(tempfile.mkdtemp(prefix="covslam-cpu-"))
    trees = {"this": Path.cwd(), "versus": args.versus.resolve()}
    servers = {
        name: TreeServer(work / name / "data", work / f"{name}.log", tree)
        for name, tree in trees.items()
    }
    try:
        for server in servers.values():
            server.start()
        clients = {name: httpx.Client(base_url=s.url, timeout=120) for name, s in servers.items()}
        maps = {
            name: [
                c.post("/v1/maps", json={"name": f"m{i}", "config": MAP_CONFIG}).json()["id"]
                for i in range(args.maps)
            ]
            for name, c in clients.items()
        }
        cpu0 = {name: _server_times(servers[name], c) for name, c in clients.items()}
        runs: dict[str, dict[str, Any]] = {}

        def post(name: str) -> None:
            runs[name] = post_all(servers[name].port, maps[name], frames, limit_s=600)[0]

        threads = [threading.Thread(target=post, args=(name,)) for name in servers]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        cpu1 = {name: _server_times(servers[name], c) for name, c in clients.items()}
    finally:
        for server in servers.values():
            server.kill()
    out: dict[str, Any] = {
        "command": "nice -n 10 python -m bench.request_cpu " + " ".join(sys.argv[1:]),
        "maps": args.maps,
        "clients_per_map": args.clients,
        "loadavg": runs["this"]["loadavg"],
    }
    for name in servers:
        n = runs[name]["frames"]
        out[name] = {
            "tree": str(trees[name]),
            "frames": n,
            "frames_per_s": runs[name]["frames_per_s"],
            "cpu_ms_per_frame": {
                who: round(
                    1e3
                    * sum(cpu1[name][who][k] - cpu0[name][who][k] for k in ("user", "system"))
                    / n,
                    3,
                )
                for who in ("api", "workers")
            },
        }
    return out


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
    if sys.argv[1:2] == ["--report"]:
        report(Path(sys.argv[2]))
        return
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--maps", type=int, default=8)
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--frames", type=int, default=150, help="per client")
    parser.add_argument("--profile", type=Path, default=None)
    parser.add_argument("--versus", type=Path, default=None, help="another checkout")
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    args = parser.parse_args()
    if args.versus is not None:
        print(json.dumps(versus(args), indent=2), flush=True)
        return
    result = run(args)
    print(json.dumps(result, indent=2), flush=True)
    if args.profile is None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "request_cpu.json").write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
