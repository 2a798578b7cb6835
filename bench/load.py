"""Under load: throughput, reads during the load, balancing, event streams, restart.

One run, one machine, so the ratios compare phases that shared whatever load it carried
(the one-minute load average is recorded with every phase). Run from the repository
root, niced (2 cores, shared)::

    nice -n 10 python -m bench.load [--maps 8] [--clients 4] [--frames 500] [--load-s 60]
                                    [--slices 6] [--event-maps 2] [--event-frames 100]
                                    [--subscribers 200] [--runs 5] [--out bench/results]
    python -m bench.load --bound-only 5   # the bound alone, 5 times: the machine's spread
    python -m bench.load --corunner 3     # the bound alone and beside a co-runner, in turn

Frames: a simulated indoor run per client (make_world rooms (2, 2), 100 landmarks,
~10 labelled bearings per frame); the clients of a map drive robots r1..rC through the
same world. Map config: landmark cap 50, the default policy. The load is the one an
outside audit put on the service: 8 maps x 4 clients for 60 s.

Phases 1 and 2 take turns, `slices` times (the machine's speed moves from one minute to
the next by up to 10 %, so a load and a bound a minute apart compare two machines):
`load-s` / `slices` seconds of phase 1, the server left to settle, then phase 2 on
exactly the frames the clients posted in that slice, and again. Each phase's figures
are summed over its slices; ``ratio_per_slice`` gives each turn's own ratio.

1. ``http``: a ``covslam serve --workers 2`` (uvicorn in a subprocess, SQLite,
   synchronous NORMAL); 12 maps are created (placed 6:6) and 4 of worker 1's deleted, so
   the load maps are placed 6:2 on the workers when their frames begin, as a placement
   by id did (``placed_at_start``; the pool deals a map again at its first frame). M maps x C
   clients post their frames (one keep-alive connection per client and slice, closed
   loop, all clients on one asyncio loop in the bench's process, the bodies encoded
   before the phase; a slice ends when its time is up and every client has its answer;
   no client runs out of frames, so every slice ends with every client still posting
   and both workers busy; ``clients_out_of_frames`` counts those that did, which would
   leave a tail of fewer maps): frames/s, POST p50/p99, per-map frames/s in the first
   third of the first slice and the last third of the last (the balancer's effect), the
   moves the pool made. Meanwhile a reader process GETs pose, landmarks, trajectory and
   the summary of an idle map and of a busy map, a round every 0.25 s: p50/p99 per
   target.
2. ``cpu_bound``: exactly the frames the clients posted, through ``MapSession.submit``
   in-process, each map with the config the service created the HTTP maps with (read
   from their record: the estimator's defaults for a new map filled in, e.g. the upkeep
   after the frame), the maps dealt to two processes (one per core, at a worker's
   niceness, kept from slice to slice with their maps), each map's robots interleaved
   frame by frame, while the server idles (``http.settle``: the waits, after each slice,
   for its workers' due snapshots and view renewals to end, and the server's CPU
   seconds meanwhile; the reader pauses too): frames/s = all frames / (the processes'
   wall times summed / 2), every core busy. ``http.ratio_to_cpu_bound`` = phase 1's
   frames/s over this. CPU time per frame (from /proc, so other work on the machine is
   not in it): the workers', the API process's and the bench's own clients' in phase 1,
   and the in-process sessions' here; ``worker_cpu_to_in_process`` compares the first
   with the last.
3. ``events``: three times `event-maps` fresh maps take the same frames from C clients
   each (`event-frames` per client): with no event stream open, with `subscribers` SSE
   streams open on them (read by one asyncio process), and with none again: frames/s
   and POST p50, the middle phase against the mean of the other two, and the CPU a
   frame of the workers, the API process (whose fan-out writes every event to every
   stream), the bench's clients and its stream reader. The maps are deleted afterwards.
4. ``restart``: SIGTERM (seconds until the process group ended), the frames each map's
   log holds beyond its latest snapshot (what a start would replay), then a start on
   the same data: seconds until /readyz answered 200 with every map loaded, and the
   same for a start with no maps (the process and import cost alone).

Writes ``<out>/load.json``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import uvloop

from service.frames_io import frame_to_dict
from service.offline.datasets.indoor_sim import make_world, simulate
from tests.support.clusters import free_port
from tests.support.snapshots import unsnapshotted

MAP_CONFIG = {"landmark_cap": 50}
READ_PATHS = ("pose", "landmarks", "trajectory", "")
READ_PAUSE_S = 0.25
"""Between two rounds of reads (a dashboard's polling, not a second load)."""


def _loadavg() -> float:
    return round(os.getloadavg()[0], 2)


def _stats(ms: list[float]) -> dict[str, float]:
    if not ms:
        return {"n": 0}
    a = np.asarray(ms)
    return {
        "n": len(a),
        "p50": round(float(np.percentile(a, 50)), 1),
        "p99": round(float(np.percentile(a, 99)), 1),
        "max": round(float(a.max()), 1),
    }


def make_frames(maps: int, clients: int, frames: int) -> list[list[list[dict[str, Any]]]]:
    """Per map, per client (robot r1..): `frames` frame dicts of one simulated run."""
    out = []
    for m in range(maps):
        rng = np.random.default_rng(100 + m)
        world = make_world(rooms=(2, 2), landmarks=100, rng=rng)
        runs = []
        for c in range(clients):
            run = simulate(world, frames=frames, rng=np.random.default_rng(1000 * m + c),
                           robot=f"r{c + 1}")  # fmt: skip
            runs.append([frame_to_dict(f) for f in run.frames])
        out.append(runs)
    return out


# ------------------------------------------------------------------ 1. CPU bound
def created_config(config: dict[str, Any] | None = None) -> dict[str, Any]:
    """The config the service creates a map with when a client posts `config` (default
    MAP_CONFIG): MapConfig.for_new_map with the service's default caps (the estimator's
    current defaults, e.g. the upkeep after the frame, where the client gave none)."""
    from service.pipeline.config import MapConfig
    from service.settings import Settings

    settings = Settings()
    doc = MapConfig.model_validate(MAP_CONFIG if config is None else config)
    new = doc.for_new_map(settings.default_landmark_cap, settings.default_camera_landmark_cap)
    return new.model_dump(mode="json")


def _sessions(n: int, config: dict[str, Any]) -> list[Any]:
    """`n` new maps' sessions in a temporary directory, each created with `config` (as
    stored in the map's record), in a process niced as a worker is."""
    from service.session import MapSession
    from service.settings import StoreSettings, WorkerSettings
    from service.store import MapRecord

    os.nice(WorkerSettings().nice)  # as a worker process: the same share of the cores
    work = Path(tempfile.mkdtemp(prefix="covslam-load-"))
    sessions = []
    for i in range(n):
        record = MapRecord(f"m{i}", f"m{i}", "mapping", dict(config), time.time())
        sessions.append(MapSession.create(work / f"m{i}.sqlite", record, StoreSettings()))
    return sessions


Figures = tuple[int, float, float, int]
"""(frames, wall s, CPU s, involuntary context switches) of a run of `_submit_all`."""


def _submit_all(sessions: list[Any], maps: list[list[list[dict[str, Any]]]]) -> Figures:
    """(frames, wall s, CPU s, involuntary context switches) of these maps' frames (per
    map, per robot) through their sessions' MapSession.submit, each map's robots
    interleaved frame by frame and the maps in turn."""
    t0, c0 = time.perf_counter(), time.process_time()
    s0 = resource.getrusage(resource.RUSAGE_SELF).ru_nivcsw
    n = 0
    for k in range(max((len(r) for runs in maps for r in runs), default=0)):
        for session, runs in zip(sessions, maps, strict=True):
            for run in runs:
                if k < len(run):
                    session.submit(run[k])
                    n += 1
    switches = resource.getrusage(resource.RUSAGE_SELF).ru_nivcsw - s0
    return n, time.perf_counter() - t0, time.process_time() - c0, switches


def _in_process(maps: list[list[list[dict[str, Any]]]], config: dict[str, Any]) -> Figures:
    """`_submit_all` of these maps' frames in new sessions (one process)."""
    return _submit_all(_sessions(len(maps), config), maps)


def _bound_process(conn: Any, n_maps: int, config: dict[str, Any]) -> None:
    """Process: `n_maps` sessions kept between slices; each message (per map, per robot,
    the frames a slice posted) is submitted and answered with `_submit_all`'s figures;
    None ends it."""
    sessions = _sessions(n_maps, config)
    conn.send(len(sessions))  # ready: the load's slices may begin
    while (maps := conn.recv()) is not None:
        conn.send(_submit_all(sessions, maps))


def _bound_rate(runs: list[Figures], cores: int) -> float:
    """Frames/s of `_submit_all` runs made side by side, every core busy all the time
    (the processes' wall times summed, shared out over the cores: their frames differ in
    number, so one finishes first)."""
    return sum(r[0] for r in runs) / (sum(r[1] for r in runs) / cores)


def _bound_figures(processes: list[Figures]) -> dict[str, Any]:
    """The bound's document from each process's figures (summed over its runs)."""
    n = sum(r[0] for r in processes)
    return {
        "frames": n,
        "process_wall_s": [round(r[1], 2) for r in processes],
        "frames_per_s": round(_bound_rate(processes, len(processes)), 1),
        "processes": len(processes),
        "cpu_ms_per_frame": round(1e3 * sum(r[2] for r in processes) / n, 2),
        "involuntary_switches_per_frame": round(sum(r[3] for r in processes) / n, 2),
    }


class SlicedBound:
    """The in-process bound kept beside the server, `cores` processes (map i in process
    i % cores), fed slice by slice the frames the clients posted in the slice before."""

    def __init__(self, n_maps: int, config: dict[str, Any], cores: int = 2) -> None:
        ctx = multiprocessing.get_context("spawn")
        self.cores = cores
        self.conns, self.procs = [], []
        for c in range(cores):
            parent, child = ctx.Pipe()
            share = len(range(c, n_maps, cores))
            proc = ctx.Process(target=_bound_process, args=(child, share, config))
            proc.start()
            self.conns.append(parent)
            self.procs.append(proc)
        for conn in self.conns:  # started, imported and its maps created
            conn.recv()

    def run(self, frames: list[list[list[dict[str, Any]]]]) -> list[Figures]:
        """Every process its maps' frames at once; their figures when all are done."""
        for c, conn in enumerate(self.conns):
            conn.send(frames[c :: self.cores])
        return [conn.recv() for conn in self.conns]

    def close(self) -> None:
        for conn in self.conns:
            conn.send(None)
        for proc in self.procs:
            proc.join(timeout=60)


def cpu_bound(
    frames: list[list[list[dict[str, Any]]]], cores: int = 2, config: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The frames through MapSession.submit in `cores` processes; `config`: the maps'
    config as the service stored it (default: `created_config()`, what a map posted with
    MAP_CONFIG gets), so that the bound runs the estimator the HTTP maps run."""
    load0 = _loadavg()
    config = created_config() if config is None else config
    shares = [frames[i::cores] for i in range(cores)]
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(cores, mp_context=ctx) as pool:
        results = list(pool.map(_in_process, shares, [config] * cores))
    return {**_bound_figures(results), "loadavg": [load0, _loadavg()]}


# ------------------------------------------------------------------ the server
class Server:
    def __init__(self, data: Path, log: Path) -> None:
        self.data, self.log = data, log
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> float:
        """`covslam serve` with two workers; seconds until /readyz answered 200."""
        return self.launch(
            ["-m", "api.cli", "serve"], {**os.environ, "COVSLAM_LOG_LEVEL": "warning"}
        )

    def launch(self, argv: list[str], env: dict[str, str], cwd: Path | None = None) -> float:
        """Start `python argv` as this server's process (its port, data directory, two
        workers); seconds until /readyz answered 200."""
        t0 = time.monotonic()
        with self.log.open("ab") as out:
            self.proc = subprocess.Popen(
                [sys.executable, *argv, "--port", str(self.port), "--data-dir", str(self.data),
                 "--workers", "2"],
                cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
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

    def kill(self) -> None:
        """SIGKILL the process group if it still runs (a failed run leaves nothing)."""
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=30)

    def stop(self) -> float:
        """SIGTERM; seconds until the process group ended."""
        assert self.proc is not None
        t0 = time.monotonic()
        os.killpg(self.proc.pid, signal.SIGTERM)
        self.proc.wait(timeout=120)
        while True:  # the workers end after the API process
            try:
                os.killpg(self.proc.pid, 0)
            except ProcessLookupError:
                return time.monotonic() - t0
            if time.monotonic() - t0 > 120:
                os.killpg(self.proc.pid, signal.SIGKILL)
                return time.monotonic() - t0
            time.sleep(0.02)


async def _post_loop(port: int, map_id: str, bodies: list[bytes], until: float,
                     out: list[tuple[float, float, str, int]], client: int) -> None:  # fmt: skip
    """Post the frames' encoded bodies in order over one keep-alive connection until done
    or `until` (monotonic); (end time, ms, map, client) each. A minimal HTTP/1.1 client on
    asyncio streams: the clients share the service's two cores, so they should cost it as
    little as a robot on its own computer would (encoded ahead, as a robot's frame is)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    head = (f"POST /v1/maps/{map_id}/frames HTTP/1.1\r\nHost: 127.0.0.1\r\n"
            "Content-Type: application/json\r\nContent-Length: ").encode()  # fmt: skip
    for body in bodies:
        if time.monotonic() >= until:
            break
        t0 = time.perf_counter()
        writer.write(head + str(len(body)).encode() + b"\r\n\r\n" + body)
        if (status := await _response(reader)) != 200:
            raise RuntimeError(f"POST {map_id}: {status}")
        out.append((time.monotonic(), 1e3 * (time.perf_counter() - t0), map_id, client))
    writer.close()
    await writer.wait_closed()


def _encoded(frames: list[list[list[dict[str, Any]]]]) -> list[list[list[bytes]]]:
    """Per map, per client, each frame's JSON body (encoded before a phase, as a robot
    has its frame ready)."""
    return [[[json.dumps(f).encode() for f in run] for run in runs] for runs in frames]


def post_all(
    port: int,
    maps: list[str],
    frames: list[list[list[dict[str, Any]]]],
    limit_s: float,
    start: list[list[int]] | None = None,
    bodies: list[list[list[bytes]]] | None = None,
) -> tuple[dict[str, Any], list[list[int]]]:
    """Every client posts its frames (at most `limit_s`), from its frame `start` on (default
    0; `bodies`: the frames already encoded): (frames/s, POST latency, ...; the frames each
    client of each map posted)."""
    rows: list[tuple[float, float, str, int]] = []
    if bodies is None:
        bodies = _encoded(frames)
    if start is None:
        start = [[0] * len(runs) for runs in frames]

    async def clients() -> None:
        await asyncio.gather(*(
            _post_loop(port, m, run[first:], until, rows, c)
            for m, runs, firsts in zip(maps, bodies, start, strict=True)
            for c, (run, first) in enumerate(zip(runs, firsts, strict=True))
        ))  # fmt: skip

    load0 = _loadavg()
    t0, cpu0 = time.monotonic(), time.process_time()
    until = t0 + limit_s
    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        runner.run(clients())
    wall, cpu = time.monotonic() - t0, time.process_time() - cpu0
    thirds = []
    for lo, hi in ((0.0, 1 / 3), (2 / 3, 1.0)):
        a, b = t0 + lo * wall, t0 + hi * wall
        per_map = [sum(1 for r in rows if r[2] == m and a <= r[0] < b) / (b - a) for m in maps]
        thirds.append({"min": round(min(per_map), 2), "max": round(max(per_map), 2)})
    posted = [
        [sum(1 for r in rows if r[2] == m and r[3] == c) for c in range(len(runs))]
        for m, runs in zip(maps, frames, strict=True)
    ]
    return {
        "frames": len(rows),
        "wall_s": round(wall, 2),
        "frames_per_s": round(len(rows) / wall, 1),
        "post_ms": _stats([r[1] for r in rows]),
        "post_ms_all": [r[1] for r in rows],
        "clients_cpu_s": round(cpu, 3),
        "per_map_frames_per_s_first_third": thirds[0],
        "per_map_frames_per_s_last_third": thirds[1],
        "loadavg": [load0, _loadavg()],
    }, posted


async def _response(reader: asyncio.StreamReader) -> int:
    """An HTTP/1.1 response's status, its body read and dropped (the bench's minimal
    keep-alive clients)."""
    status = int((await reader.readline()).split()[1])
    length, chunked = 0, False
    while (line := await reader.readline()) not in (b"\r\n", b""):
        name, _, value = line.partition(b":")
        name = name.strip().lower()
        if name == b"content-length":
            length = int(value)
        elif name == b"transfer-encoding" and b"chunked" in value.lower():
            chunked = True
    if not chunked:
        await reader.readexactly(length)
        return status
    while size := int((await reader.readline()).split(b";")[0], 16):
        await reader.readexactly(size + 2)
    await reader.readline()  # the empty trailer
    return status


async def _get(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, path: str) -> int:
    """One GET over a keep-alive connection; its status."""
    writer.write(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
    return await _response(reader)


async def _read_rounds(
    port: int, targets: dict[str, str], stop: Any, go: Any
) -> dict[str, list[float]]:
    """`_reader`'s rounds: ms per GET, per target (a connection per slice: the server
    closes one left idle through the bound's turn)."""
    out: dict[str, list[float]] = {name: [] for name in targets}
    connection = None
    while not stop.is_set():
        if not go.is_set():
            if connection is not None:
                connection[1].close()
                connection = None
            await asyncio.sleep(0.1)
            continue
        if connection is None:
            connection = await asyncio.open_connection("127.0.0.1", port)
        for name, map_id in targets.items():
            for path in READ_PATHS:
                t0 = time.perf_counter()
                url = f"/v1/maps/{map_id}" + (f"/{path}" if path else "")
                status = await _get(*connection, url)
                out[name].append(1e3 * (time.perf_counter() - t0))
                if status != 200:
                    raise RuntimeError(f"GET {path}: {status}")
        await asyncio.sleep(READ_PAUSE_S)
    return out


def _reader(port: int, targets: dict[str, str], stop: Any, queue: Any, go: Any) -> None:
    """Process: GET each read path of each target map in turn until `stop` is set, while
    `go` is (the load's slices, not the bound's); one keep-alive connection, so that the
    bench's dashboard takes as little of the service's cores as it can."""
    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        queue.put(runner.run(_read_rounds(port, targets, stop, go)))


async def _subscribe(port: int, paths: list[str], stop: Any, counts: Any) -> None:
    async def one(path: str) -> int:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(
            f"GET {path} HTTP/1.1\r\nHost: x\r\nAccept: text/event-stream\r\n\r\n".encode()
        )
        await writer.drain()
        seen = 0
        while not stop.is_set():
            try:
                chunk = await asyncio.wait_for(reader.read(1 << 16), 0.5)
            except TimeoutError:
                continue
            if not chunk:
                break
            seen += chunk.count(b"\nevent: frame\n")
        writer.close()
        return seen

    results = await asyncio.gather(*(one(p) for p in paths))
    counts.put(sum(results))


def _subscribers(port: int, paths: list[str], stop: Any, counts: Any) -> None:
    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        runner.run(_subscribe(port, paths, stop, counts))


def _cpu_s(pid: int) -> float:
    """CPU seconds (user + system) a process has used so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _process_cpu_s(proc: Any) -> float:
    """`_cpu_s` of a started multiprocessing process; 0 for None."""
    return 0.0 if proc is None or proc.pid is None else _cpu_s(proc.pid)


def _switches(pid: int) -> int:
    """Involuntary context switches of a process so far (all its threads)."""
    total = 0
    for status in Path(f"/proc/{pid}/task").glob("*/status"):
        for line in status.read_text().splitlines():
            if line.startswith("nonvoluntary_ctxt_switches"):
                total += int(line.split()[1])
    return total


def _worker_pids(client: httpx.Client) -> list[int]:
    return [w["pid"] for w in client.get("/v1/workers").json()["workers"]]


def _server_cpu(server: Server, workers: list[int]) -> dict[str, float]:
    """CPU seconds so far of the API process and of the `workers` (pids; summed)."""
    assert server.proc is not None
    return {"api": _cpu_s(server.proc.pid), "workers": sum(_cpu_s(p) for p in workers)}


def _settle(server: Server, client: httpx.Client, limit_s: float = 60.0) -> dict[str, float]:
    """Wait until the server's processes are idle (the workers take their due snapshots
    and renew the views that lag once the frames stop), at most `limit_s`: the seconds
    waited and the CPU seconds the server used meanwhile. The in-process bound runs
    beside an idle server, not one still busy with the load phase's aftermath."""
    t0, workers = time.monotonic(), _worker_pids(client)
    first = before = now = sum(_server_cpu(server, workers).values())
    while time.monotonic() - t0 < limit_s:
        time.sleep(1.0)
        now = sum(_server_cpu(server, workers).values())
        if now - before < 0.02:  # under 2 % of a core over the last second
            break
        before = now
    return {"s": round(time.monotonic() - t0, 1), "server_cpu_s": round(now - first, 2)}


def _unreplayed(data: Path) -> dict[str, int]:
    """Per map file: log frames after its latest snapshot (a start replays them)."""
    return {p.stem: unsnapshotted(p) for p in sorted((data / "maps").glob("*.sqlite"))}


def run(args: argparse.Namespace) -> dict[str, Any]:
    frames = make_frames(args.maps + 1, args.clients, max(args.frames, args.event_frames, 100))
    result: dict[str, Any] = {
        "command": "python -m bench.load " + " ".join(sys.argv[1:]),
        "cpu_count": os.cpu_count(),
        "maps": args.maps,
        "clients_per_map": args.clients,
        "frames_per_client": args.frames,
        "map_config": MAP_CONFIG,
    }

    ratios = []
    for k in range(args.runs):
        work = Path(tempfile.mkdtemp(prefix="covslam-load-"))
        server = Server(work / "data", work / "server.log")
        server.start()
        try:
            # the last run measures every phase; the runs before it phases 1 and 2
            got = _measure(args, frames, server, dict(result), whole=k == args.runs - 1)
        finally:
            server.kill()
        ratios.append(got["http"]["ratio_to_cpu_bound"])
    # The machine's speed moves from minute to minute and the load phase and the bound
    # run a minute apart: one run's ratio moves with it, the median of several less.
    got["ratio_runs"] = ratios
    got["ratio_median"] = round(float(np.median(ratios)), 3)
    return got


def _measure(
    args: argparse.Namespace,
    frames: list[list[list[dict[str, Any]]]],
    server: Server,
    result: dict[str, Any],
    whole: bool = True,
) -> dict[str, Any]:
    """Phases 1-4 (`whole`; else 1 and 2) against the started `server`; `result` filled
    in and returned."""
    main = frames[: args.maps]
    work = server.data.parent
    client = httpx.Client(base_url=server.url, timeout=120)
    ids = [client.post("/v1/maps", json={"name": f"m{i}", "config": MAP_CONFIG}).json()["id"]
           for i in range(12)]  # fmt: skip
    worker = {m: client.get(f"/v1/maps/{m}").json()["worker"] for m in ids}
    on_1 = [m for m in ids if worker[m] == 1]
    for m in on_1[:4]:
        client.delete(f"/v1/maps/{m}")
    maps = [m for m in ids if m not in on_1[:4]][: args.maps]
    placed = [sum(1 for m in maps if worker[m] == w) for w in (0, 1)]
    # the idle map: the first frames of one more run, and two small maps (11 in all)
    idle = client.post("/v1/maps", json={"name": "idle", "config": MAP_CONFIG}).json()["id"]
    for f in frames[-1][0][:100]:
        client.post(f"/v1/maps/{idle}/frames", json=f).raise_for_status()
    small = []
    for k in range(2):
        m = client.post("/v1/maps", json={"name": f"small{k}", "config": MAP_CONFIG}).json()["id"]
        for f in frames[-1][(k + 1) % args.clients][:30]:
            client.post(f"/v1/maps/{m}/frames", json=f).raise_for_status()
        small.append(m)

    ctx = multiprocessing.get_context("spawn")
    stop, queue, go = ctx.Event(), ctx.Queue(), ctx.Event()
    reader = ctx.Process(target=_reader, args=(server.port, {"idle": idle, "busy": maps[0]},
                                               stop, queue, go))  # fmt: skip
    reader.start()
    # the maps' config as the service created them (the estimator's defaults filled in)
    config = client.get(f"/v1/maps/{maps[0]}").json()["config"]
    bound = SlicedBound(len(maps), config)
    bodies = _encoded(main)
    at = [[0] * len(runs) for runs in main]
    pids = _worker_pids(client)
    slices, bounds, settles = [], [], []
    cpu = {"workers": 0.0, "api": 0.0, "clients": 0.0, "reader": 0.0, "switches": 0.0}
    load0 = _loadavg()
    try:
        for _ in range(args.slices):
            # 1. the clients post for a slice of the load's time, the reads beside them
            go.set()
            switches0, cpu0 = sum(_switches(p) for p in pids), _server_cpu(server, pids)
            reader0 = _process_cpu_s(reader)
            part, posted = post_all(server.port, maps, main, args.load_s / args.slices,
                                    start=at, bodies=bodies)  # fmt: skip
            cpu1, switches1 = _server_cpu(server, pids), sum(_switches(p) for p in pids)
            go.clear()
            for key in ("workers", "api"):
                cpu[key] += cpu1[key] - cpu0[key]
            cpu["clients"] += part.pop("clients_cpu_s")
            cpu["reader"] += _process_cpu_s(reader) - reader0
            cpu["switches"] += switches1 - switches0
            settles.append(_settle(server, client))
            # 2. the same frames in-process, while the server idles
            done = [
                [run[a : a + n] for run, a, n in zip(runs, starts, ns, strict=True)]
                for runs, starts, ns in zip(main, at, posted, strict=True)
            ]
            bounds.append(bound.run(done))
            at = [
                [a + n for a, n in zip(firsts, ns, strict=True)]
                for firsts, ns in zip(at, posted, strict=True)
            ]
            slices.append(part)
    finally:
        bound.close()
        stop.set()
        go.set()
    reads = queue.get(timeout=60)
    reader.join()
    n = sum(p["frames"] for p in slices)
    http_wall = sum(p["wall_s"] for p in slices)
    http_run: dict[str, Any] = {
        "frames": n,
        "wall_s": round(http_wall, 2),
        "frames_per_s": round(n / http_wall, 1),
        "slices": args.slices,
        "post_ms": _stats([ms for p in slices for ms in p.pop("post_ms_all")]),
        # the balancer's effect: per map, the first third of the first slice and the
        # last third of the last
        "per_map_frames_per_s_first_third": slices[0]["per_map_frames_per_s_first_third"],
        "per_map_frames_per_s_last_third": slices[-1]["per_map_frames_per_s_last_third"],
        "loadavg": [load0, _loadavg()],
    }
    http_run["placed_at_start"] = placed
    http_run["clients_out_of_frames"] = sum(
        a == len(run)
        for runs, starts in zip(main, at, strict=True)
        for run, a in zip(runs, starts, strict=True)
    )
    status = client.get("/v1/workers").json()
    http_run["moves"] = status.get("moves")
    http_run["maps_per_worker_after"] = [
        sum(1 for m in w["maps"] if m in maps) for w in status["workers"]
    ]
    http_run["reads_ms"] = {name: _stats(ms) for name, ms in reads.items()}
    http_run["reads_ms"]["all"] = _stats([v for ms in reads.values() for v in ms])
    http_run["settle"] = {
        "s": round(sum(x["s"] for x in settles), 1),
        "server_cpu_s": round(sum(x["server_cpu_s"] for x in settles), 2),
    }
    print("http", http_run, flush=True)
    # each bound process's figures summed over the slices
    per_process = [
        (sum(b[c][0] for b in bounds), sum(b[c][1] for b in bounds),
         sum(b[c][2] for b in bounds), sum(b[c][3] for b in bounds))
        for c in range(bound.cores)
    ]  # fmt: skip
    result["cpu_bound"] = _bound_figures(per_process)
    print("cpu bound", result["cpu_bound"], flush=True)
    http_run["ratio_to_cpu_bound"] = round(
        http_run["frames_per_s"] / result["cpu_bound"]["frames_per_s"], 3
    )
    # each slice's ratio: how far the machine's speed moved between the slices
    http_run["ratio_per_slice"] = [
        round(p["frames"] / p["wall_s"] / _bound_rate(b, bound.cores), 3)
        for p, b in zip(slices, bounds, strict=True)
    ]
    http_run["cpu_ms_per_frame"] = {
        "workers": round(1e3 * cpu["workers"] / n, 2),
        "api_process": round(1e3 * cpu["api"] / n, 2),
        "bench_clients": round(1e3 * cpu["clients"] / n, 2),
        "bench_reader": round(1e3 * cpu["reader"] / n, 2),
    }
    http_run["worker_involuntary_switches_per_frame"] = round(cpu["switches"] / n, 2)
    # the same frames' CPU in a worker against in-process (no other load in the figure)
    http_run["worker_cpu_to_in_process"] = round(
        http_run["cpu_ms_per_frame"]["workers"] / result["cpu_bound"]["cpu_ms_per_frame"], 3
    )
    result["http"] = http_run
    if not whole:
        return result

    # 3. events: fresh maps, the same frames, 0 subscribers, then `subscribers`, then 0
    events: dict[str, Any] = {}
    phase = [[run[: args.event_frames] for run in runs] for runs in frames[: args.event_maps]]
    for k, n_subs in enumerate((0, args.subscribers, 0)):
        fresh = [
            client.post("/v1/maps", json={"name": f"e{k}{i}", "config": MAP_CONFIG}).json()["id"]
            for i in range(args.event_maps)
        ]
        proc = None
        stop, counts = ctx.Event(), ctx.Queue()
        if n_subs:
            paths = [f"/v1/maps/{fresh[i % len(fresh)]}/events" for i in range(n_subs)]
            proc = ctx.Process(target=_subscribers, args=(server.port, paths, stop, counts))
            proc.start()
            time.sleep(3.0)  # let them connect
        name = f"{k + 1}_subscribers_{n_subs}"
        cpu0 = _server_cpu(server, pids)
        subs0 = _process_cpu_s(proc)
        events[name] = post_all(server.port, fresh, phase, limit_s=600)[0]
        cpu1 = _server_cpu(server, pids)
        n = events[name]["frames"]
        events[name].pop("post_ms_all")
        # CPU a frame: the service's processes, and the bench's stream reader beside them
        events[name]["cpu_ms_per_frame"] = {
            "workers": round(1e3 * (cpu1["workers"] - cpu0["workers"]) / n, 2),
            "api_process": round(1e3 * (cpu1["api"] - cpu0["api"]) / n, 2),
            "bench_clients": round(1e3 * events[name].pop("clients_cpu_s") / n, 2),
            "bench_streams": round(1e3 * (_process_cpu_s(proc) - subs0) / n, 2),
        }
        if proc is not None:
            stop.set()
            events[name]["frame_events_received"] = counts.get(timeout=60)
            proc.join()
        for m in fresh:
            client.delete(f"/v1/maps/{m}").raise_for_status()
    zeros = [events["1_subscribers_0"], events["3_subscribers_0"]]
    many = events[f"2_subscribers_{args.subscribers}"]
    zero_p50 = float(np.mean([z["post_ms"]["p50"] for z in zeros]))
    zero_rate = float(np.mean([z["frames_per_s"] for z in zeros]))
    # against the mean of the phases before and after (the machine's load drifts)
    events["post_p50_ratio"] = round(many["post_ms"]["p50"] / zero_p50, 3)
    events["throughput_ratio"] = round(many["frames_per_s"] / zero_rate, 3)
    result["events"] = events
    print("events", events, flush=True)
    client.close()

    # 4. restart
    stop_s = server.stop()
    unreplayed = _unreplayed(work / "data")
    load0 = _loadavg()
    ready_s = server.start()
    n_maps = len(httpx.get(server.url + "/v1/maps").json())
    server.stop()
    empty = Server(work / "empty", work / "empty.log")
    empty_s = empty.start()
    empty.stop()
    result["restart"] = {
        "maps": n_maps,
        "sigterm_to_exit_s": round(stop_s, 2),
        "log_frames_after_latest_snapshot": unreplayed,
        "ready_s": round(ready_s, 2),
        "ready_s_no_maps": round(empty_s, 2),
        "loadavg": [load0, _loadavg()],
    }
    print("restart", result["restart"], flush=True)
    return result


def bound_only(maps: int, clients: int, repeats: int) -> dict[str, Any]:
    """The in-process bound `repeats` times in a row on the same frames, nothing else
    running: how much the machine's own speed moves between runs a minute apart (the
    spread the load phase's ratio to its bound inherits)."""
    frames = make_frames(maps, clients, 175)
    runs = [cpu_bound(frames) for _ in range(repeats)]
    fps = [r["frames_per_s"] for r in runs]
    return {
        "command": "python -m bench.load " + " ".join(sys.argv[1:]),
        "frames": runs[0]["frames"],
        "frames_per_s": fps,
        "cpu_ms_per_frame": [r["cpu_ms_per_frame"] for r in runs],
        "max_over_min": round(max(fps) / min(fps), 3),
        "runs": runs,
    }


def _corunner(wakes_per_s: float, work_ms: float, stop: Any) -> None:
    """Process: like the API process beside the workers, `wakes_per_s` wake-ups a second,
    each `work_ms` of CPU on Python objects (JSON-encoding small documents)."""
    rng = np.random.default_rng(0)
    docs = [{f"k{i}": rng.random(20).tolist()} for i in range(3000)]
    i = 0
    while not stop.is_set():
        t0 = time.thread_time()
        while time.thread_time() - t0 < work_ms / 1e3:
            json.dumps(docs[i % len(docs)])
            i += 37
        time.sleep(1.0 / wakes_per_s)


def beside_corunner(maps: int, clients: int, pairs: int) -> dict[str, Any]:
    """The in-process bound alone and beside `_corunner` (1 000 wake-ups a second, 0.2 ms
    each: 20 % of a core), in turn, `pairs` times: whether sharing the cores with a
    process that wakes as often as the API process slows the estimator's CPU per frame."""
    frames = make_frames(maps, clients, 175)
    ctx = multiprocessing.get_context("spawn")
    runs: dict[str, list[dict[str, Any]]] = {"alone": [], "beside": []}
    for _ in range(pairs):
        runs["alone"].append(cpu_bound(frames))
        stop = ctx.Event()
        proc = ctx.Process(target=_corunner, args=(1000.0, 0.2, stop))
        proc.start()
        try:
            runs["beside"].append(cpu_bound(frames))
        finally:
            stop.set()
            proc.join(timeout=30)
    return {
        "command": "python -m bench.load " + " ".join(sys.argv[1:]),
        "frames": runs["alone"][0]["frames"],
        "corunner": {"wakes_per_s": 1000, "cpu_ms_per_wake": 0.2},
        **{
            f"{name}_{key}": [r[key] for r in rs]
            for name, rs in runs.items()
            for key in ("cpu_ms_per_frame", "involuntary_switches_per_frame", "frames_per_s")
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--maps", type=int, default=8)
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--frames", type=int, default=500, help="at most, per client (1-2)")
    parser.add_argument("--load-s", type=float, default=60.0, help="length of phase 1")
    parser.add_argument(
        "--slices", type=int, default=6, help="phase 1 in this many turns with phase 2"
    )
    parser.add_argument("--event-maps", type=int, default=2)
    parser.add_argument("--event-frames", type=int, default=100, help="per client (phase 3)")
    parser.add_argument("--subscribers", type=int, default=200)
    parser.add_argument(
        "--runs",
        type=int,
        choices=range(1, 21),
        default=5,
        metavar="1-20",
        help="runs of phases 1-2 (the last also 3-4)",
    )
    parser.add_argument(
        "--bound-only",
        type=int,
        default=0,
        metavar="N",
        help="no server: the in-process bound N times on the same frames (the first 175 of "
        "each client's run, about what a load phase posts); writes load_bound_only.json",
    )
    parser.add_argument(
        "--corunner",
        type=int,
        default=0,
        metavar="N",
        help="no server: the bound alone and beside a process waking 1000 times a second, "
        "N times in turn; writes load_corunner.json",
    )
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    args = parser.parse_args()
    if args.corunner:
        args.out.mkdir(parents=True, exist_ok=True)
        doc = beside_corunner(args.maps, args.clients, args.corunner)
        (args.out / "load_corunner.json").write_text(json.dumps(doc, indent=2) + "\n")
        return
    if args.bound_only:
        args.out.mkdir(parents=True, exist_ok=True)
        doc = bound_only(args.maps, args.clients, args.bound_only)
        (args.out / "load_bound_only.json").write_text(json.dumps(doc, indent=2) + "\n")
        return
    result = run(args)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "load.json").write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
