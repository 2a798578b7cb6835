"""What publishing a map's view costs a frame: a worker's answer against the session alone.

The same frames (bench.load's simulated runs: `--maps` maps x `--clients` robots,
`--frames` each) go through two sets of maps in one process, frame by frame in turn:
one set through ``MapSession.submit`` alone (what bench.load's in-process bound runs),
the other through a pool worker's ``call`` (the frame, then the view it publishes) and
the pickling of its answer as the worker sends it; the API process's unpickling is timed
apart. Taking turns frame by frame, both sets meet the same load on the machine, so the
difference is the cost of the answer, not of whatever else ran. CPU time of this thread
per frame, in blocks of frames (a map's view grows with it), and the answer's bytes::

    nice -n 10 python -m bench.published_views [--maps 4] [--clients 4] [--frames 150]

Writes ``<out>/published_views.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.load import MAP_CONFIG, created_config, make_frames
from service import worker
from service.requests import CreateMap, SubmitFrame
from service.settings import Settings
from service.store import MapRecord

BLOCKS = 3
"""The frames are reported in this many blocks, first to last."""


def run(args: argparse.Namespace) -> dict[str, Any]:
    frames = make_frames(args.maps, args.clients, args.frames)
    settings = Settings(data_dir=Path(tempfile.mkdtemp(prefix="covslam-views-")))
    worker.init_worker(settings.model_dump(mode="json"), 0, own_signals=False)
    worker._publish = True  # as in a pool's worker
    config = created_config()  # what the service creates a map posted with MAP_CONFIG with
    for i in range(args.maps):
        for kind in ("session", "worker"):
            record = MapRecord(f"{kind}{i}", f"m{i}", "mapping", config, time.time())
            worker.call(record.id, CreateMap(record.as_dict()))
    sessions = worker._sessions
    load0 = round(os.getloadavg()[0], 2)
    rows: list[dict[str, float]] = []
    for k in range(args.frames):
        row = {"session": 0.0, "worker": 0.0, "unpickle": 0.0, "bytes": 0.0, "n": 0.0}
        for i, runs in enumerate(frames):
            for run_ in runs:
                t0 = time.thread_time()
                sessions[f"session{i}"].submit(run_[k])
                t1 = time.thread_time()
                sent = pickle.dumps(
                    (1, worker.call(f"worker{i}", SubmitFrame(run_[k]))), protocol=5
                )
                t2 = time.thread_time()
                pickle.loads(sent)
                t3 = time.thread_time()
                row["session"] += t1 - t0
                row["worker"] += t2 - t1
                row["unpickle"] += t3 - t2
                row["bytes"] += len(sent)
                row["n"] += 1
        rows.append(row)
    blocks = []
    size = -(-len(rows) // BLOCKS)
    for b in range(BLOCKS):
        part = rows[b * size : (b + 1) * size]
        n = sum(r["n"] for r in part)
        session_ms = 1e3 * sum(r["session"] for r in part) / n
        worker_ms = 1e3 * sum(r["worker"] for r in part) / n
        blocks.append(
            {
                "frames_per_robot": [b * size, min(len(rows), (b + 1) * size)],
                "session_ms": round(session_ms, 3),
                "worker_ms": round(worker_ms, 3),
                "answer_ms": round(worker_ms - session_ms, 3),
                "unpickle_ms": round(1e3 * sum(r["unpickle"] for r in part) / n, 3),
                "answer_bytes": round(sum(r["bytes"] for r in part) / n),
            }
        )
    return {
        "command": "nice -n 10 python -m bench.published_views " + " ".join(sys.argv[1:]),
        "maps": args.maps,
        "clients_per_map": args.clients,
        "frames_per_client": args.frames,
        "map_config": MAP_CONFIG,
        "loadavg": [load0, round(os.getloadavg()[0], 2)],
        "per_frame": blocks,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--maps", type=int, default=4)
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--frames", type=int, default=150, help="per client")
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    args = parser.parse_args()
    result = run(args)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "published_views.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result["per_frame"], indent=1))


if __name__ == "__main__":
    main()
