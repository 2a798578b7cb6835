"""MRCLAM-6, all five robots, posted into one map of a running `covslam serve`.

The robots ran at the same time, so their frames are merged by stamp and posted in
that order (one client; a robot's frames stay in its seq order). The map is created
as ``covslam replay mrclam --url`` creates its own: the given cap and policy, the
Huber loss, MRCLAM's odometry noise (``mrclam_noise``). Prints the map id, the HTTP
latency summary and each robot's ATE RMSE against Vicon as JSON; used to make the
dashboard screenshots (``bench.dashboard_screenshots``)::

    python -m bench.mrclam_http_all --url http://127.0.0.1:8000 [--cap 8] [--policy coverage]

``--map-id ID`` posts into an existing map instead (e.g. to go on after the client or the
service was stopped): frames it already holds are answered from its log, (robot, seq)
being idempotent.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

from graph.config import SlamConfig
from graph.types import FrameInput
from service.offline.datasets.mrclam import (
    default_mrclam_dir,
    load_mrclam,
    mrclam_frames,
    mrclam_noise,
)
from service.offline.evaluation import Trajectory, ate_rmse, read_tum
from service.offline.http_client import fetch_tum, replay_http


def merged_frames(directory: Path, robots: list[int]) -> tuple[list[FrameInput], dict[str, Any]]:
    """Every robot's frames merged by stamp (stable: ties keep robot order); ground truths."""
    frames: list[FrameInput] = []
    truth: dict[str, Trajectory] = {}
    for robot in robots:
        mine, gt = mrclam_frames(load_mrclam(directory, robot))
        frames.extend(mine)
        truth[f"r{robot}"] = gt
    frames.sort(key=lambda f: f.stamp)
    return frames, truth


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--url", required=True, help="the service, e.g. http://127.0.0.1:8000")
    ap.add_argument("--data", type=Path, default=None, help="MRCLAM-6 folder")
    ap.add_argument("--robots", default="1,2,3,4,5", help="comma-separated, 1-5")
    ap.add_argument("--cap", type=int, default=8, help="landmark cap")
    ap.add_argument("--policy", default="coverage")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--map-id", help="post into this existing map")
    ap.add_argument("--progress", action="store_true")
    args = ap.parse_args(argv)
    robots = [int(r) for r in args.robots.split(",")]
    frames, truth = merged_frames(args.data or default_mrclam_dir(), robots)
    default = SlamConfig()
    config = {
        "landmark_cap": args.cap,
        "policy": args.policy,
        "seed": args.seed,
        "noise": {"huber_k": default.huber_k, **mrclam_noise()},
    }
    name = f"MRCLAM-6 robots {args.robots}, bearing-only, cap {args.cap}, {args.policy}"
    run = replay_http(
        frames,
        url=args.url,
        map_id=args.map_id,
        name=name,
        config=config,
        progress=args.progress,
    )
    ate: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for robot, gt in truth.items():
            path = Path(tmp) / f"{robot}.tum"
            path.write_text(fetch_tum(args.url, run.map_id, robot))
            ate[robot] = ate_rmse(read_tum(path), gt)
    report = {"map": run.map_id, "frames": len(frames), "http": run.summary(), "ate_rmse_m": ate}
    sys.stdout.write(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
