"""Long-term landmark memory on UTIAS MRCLAM dataset 6, bearing-only, landmark cap 8.

Per robot and policy: ATE RMSE (unaligned: every run is anchored at ground truth on
its first frame; and after a least-squares SE(2) alignment), removals, restorations
of archived landmarks, landmark ids handed out, median ms per frame and the replay's
CPU seconds (the machine may be shared: CPU time is the fairer comparison). Odometry noise:
graph defaults plus MRCLAM's heading drift (service.offline.datasets.mrclam.mrclam_noise).

    python -m bench.archive_mrclam --restore on  --out bench/results/archive_mrclam_on.json
    python -m bench.archive_mrclam --restore off --out bench/results/archive_mrclam_off.json

`--restore on|off` sets SlamConfig.restore_archived; `--restore default` passes
nothing (the code's default; also runs on a tree without the archive, as "before").
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np

from graph.config import SlamConfig
from service.offline.datasets.mrclam import (
    default_mrclam_dir,
    load_mrclam,
    mrclam_frames,
    mrclam_noise,
)
from service.offline.evaluation import ate_rmse
from service.offline.replay import replay

POLICIES = ("information", "coverage")


def run_robot(
    robot: int,
    policies: tuple[str, ...],
    seeds: int,
    restore: str,
    hysteresis: dict[str, int],
    directory: Path,
) -> dict[str, Any]:
    frames, gt = mrclam_frames(load_mrclam(directory, robot))
    name = f"r{robot}"
    row: dict[str, Any] = {"frames": len(frames)}
    extra: dict[str, Any] = (
        {} if restore == "default" else {"restore_archived": restore == "on", **hysteresis}
    )
    for policy in policies:
        runs = []
        for seed in range(seeds if policy == "coverage" else 1):
            t, cpu = time.perf_counter(), time.process_time()
            cfg = SlamConfig(landmark_cap=8, policy=policy, **mrclam_noise(), **extra)
            res = replay(frames, config=cfg, seed=seed, progress=False)
            traj = res.trajectory(name)
            runs.append(
                {
                    "seed": seed,
                    "ate_m": ate_rmse(traj, gt),
                    "ate_aligned_m": ate_rmse(traj, gt, align=True),
                    "removals": res.slam.removal_count,
                    "restorations": getattr(res.slam, "restoration_count", 0),
                    "landmark_ids": res.slam._next_landmark_id,
                    "archived": len(getattr(res.slam, "archive", ())),
                    "median_frame_ms": float(np.median(res.frame_ms)),
                    "seconds": time.perf_counter() - t,
                    "cpu_seconds": time.process_time() - cpu,
                }
            )
        row[policy] = runs
    return row


def summarise(rows: dict[str, dict[str, Any]], policies: tuple[str, ...]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for policy in policies:
        runs = [r for row in rows.values() for r in row[policy]]
        out[policy] = {
            key: float(np.mean([r[key] for r in runs]))
            for key in (
                "ate_m",
                "ate_aligned_m",
                "removals",
                "restorations",
                "landmark_ids",
                "cpu_seconds",
            )
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--restore", choices=("on", "off", "default"), default="default")
    parser.add_argument("--robots", default="1,2,3,4,5")
    parser.add_argument("--policies", default=",".join(POLICIES))
    parser.add_argument("--seeds", type=int, default=1, help="seeds of the coverage policy")
    parser.add_argument(
        "--after-frames", type=int, default=None, help="SlamConfig.restore_after_frames"
    )
    parser.add_argument("--min-rays", type=int, default=None, help="SlamConfig.restore_min_rays")
    parser.add_argument("--data", type=Path, default=default_mrclam_dir())
    parser.add_argument("--out", type=Path, default=Path("bench/results/archive_mrclam.json"))
    parser.add_argument("--jobs", type=int, default=1, help="robots replayed in parallel")
    args = parser.parse_args()
    if not args.data.is_dir():
        raise SystemExit(f"MRCLAM data not found at {args.data} (set COVSLAM_DATA)")
    robots = [int(r) for r in args.robots.split(",")]
    policies = tuple(args.policies.split(","))
    hysteresis = {
        name: value
        for name, value in (
            ("restore_after_frames", args.after_frames),
            ("restore_min_rays", args.min_rays),
        )
        if value is not None
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    rows: dict[str, dict[str, Any]] = {}
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        futures = {
            pool.submit(run_robot, r, policies, args.seeds, args.restore, hysteresis, args.data): r
            for r in robots
        }
        for future in as_completed(futures):
            robot = futures[future]
            rows[f"r{robot}"] = future.result()
            print(f"r{robot}: {json.dumps(rows[f'r{robot}'])}", flush=True)
            doc = {
                "rows": dict(sorted(rows.items())),
                "summary": summarise(rows, policies),
                "complete": len(rows) == len(robots),
                "protocol": {
                    "robots": robots,
                    "policies": policies,
                    "seeds": args.seeds,
                    "restore": args.restore,
                    "hysteresis": hysteresis,
                    "landmark_cap": 8,
                    "jobs": args.jobs,
                },
                "machine": {
                    "cpus": os.cpu_count(),
                    "loadavg_at_write": os.getloadavg(),
                    "platform": platform.platform(),
                    "numpy": np.__version__,
                    "date": dt.date.today().isoformat(),
                },
            }
            args.out.write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
