"""Why the bounded graph misses batch accuracy on MRCLAM-6: pose-window variants.

Uncapped covslam (every landmark kept) on robots 1-5, bearing-only, for: the default
bounded graph (a 100-pose window grown while its poses hold fewer than 900 bearing
factors, `uncapped_window_observations`, up to 600 poses; + keyframes), the 100-pose
window alone, a 200-pose window, every pose kept, and `keyframe_for_candidate_rays` (a
pose holding a candidate's first ray stays as a keyframe, 100-pose window); dead
reckoning for reference. Each robot's run is
replayed whole and also from later start frames (`--starts`; anchored at ground truth
there, as the whole run is at its first frame): one run per robot is a single, chaotic
sample. Per run: ATE
RMSE, median ms per frame, and the final error of every landmark against the
surveyed map (a group of landmarks off together is the signature of information
marginalised at a wrong estimate).

    python -m bench.window_study [--robots 1,2,3,4,5] [--starts 0,200,500,800]
                                 [--jobs 2] [--variants default,window_100] [--out bench/results]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from bench.lifelong import machine_info
from graph.config import SlamConfig
from graph.types import FrameInput, Pose2D
from service.offline.datasets.mrclam import (
    default_mrclam_dir,
    load_mrclam,
    mrclam_frames,
    mrclam_noise,
)
from service.offline.evaluation import ate_rmse, dead_reckoning, interpolate
from service.offline.replay import replay

log = logging.getLogger("bench.window_study")

VARIANTS: dict[str, dict[str, Any]] = {
    "dead_reckoning": {},
    "default": {},
    "window_100": {"uncapped_window_observations": None},
    "window_200": {"pose_window": 200, "uncapped_window_observations": None},
    "every_pose": {"pose_window": None},
    "keyframe_for_candidate_rays": {
        "keyframe_for_candidate_rays": True,
        "uncapped_window_observations": None,
    },
}


def _from(frames: list[FrameInput], gt: Any, start: int) -> list[FrameInput]:
    """The frames from `start` on, the first anchored at ground truth (no odometry)."""
    if start == 0:
        return frames
    ok, truth = interpolate(gt, [frames[start].stamp], max_gap_s=1.0)
    if not ok[0]:
        raise ValueError(f"no ground truth at frame {start}")
    pose = Pose2D(float(truth.xy[0, 0]), float(truth.xy[0, 1]), float(truth.theta[0]))
    first = dataclasses.replace(frames[start], odometry=None, initial_pose=pose)
    return [first, *frames[start + 1 :]]


def run(robot: int, start: int, variant: str, directory: Path) -> dict[str, Any]:
    data = load_mrclam(directory, robot)
    whole, gt = mrclam_frames(data)
    frames = _from(whole, gt, start)
    row: dict[str, Any] = {"robot": robot, "start": start, "variant": variant}
    if variant == "dead_reckoning":
        return {**row, "ate_m": ate_rmse(dead_reckoning(frames), gt)}
    assert data.landmarks is not None
    surveyed = {str(int(s)): np.array([x, y]) for s, x, y in data.landmarks}
    config = SlamConfig(**{"landmark_cap": None, **mrclam_noise(), **VARIANTS[variant]})
    t = time.process_time()
    res = replay(frames, config=config, progress=False)
    slam = res.slam
    errors = {
        rec.label: float(np.hypot(*(slam.landmark_position(lid) - surveyed[rec.label])))
        for lid, rec in slam.landmarks.items()
        if rec.label in surveyed
    }
    return {
        **row,
        "ate_m": ate_rmse(res.trajectory(f"r{robot}"), gt),
        "median_ms": float(np.median(res.frame_ms)),
        "cpu_s": time.process_time() - t,
        "landmark_error_m": dict(sorted(errors.items(), key=lambda kv: int(kv[0]))),
    }


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--robots", default="1,2,3,4,5")
    parser.add_argument("--starts", default="0,200,500,800")
    parser.add_argument("--data", type=Path, default=default_mrclam_dir())
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument(
        "--variants",
        default=",".join(VARIANTS),
        help="comma-separated subset of the variants (dead reckoning is always run)",
    )
    args = parser.parse_args()
    variants = ["dead_reckoning", *(v for v in args.variants.split(",") if v != "dead_reckoning")]
    unknown = set(variants) - set(VARIANTS)
    if unknown:
        raise SystemExit(f"unknown variants {sorted(unknown)}; known: {', '.join(VARIANTS)}")
    if not args.data.is_dir():
        raise SystemExit(f"MRCLAM data not found at {args.data} (set COVSLAM_DATA)")
    robots = [int(r) for r in args.robots.split(",")]
    starts = [int(s) for s in args.starts.split(",")]
    jobs = [(r, s, v) for v in variants for s in starts for r in robots]
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        rows = list(pool.map(run, *zip(*jobs, strict=True), [args.data] * len(jobs)))
    drift = {(r["robot"], r["start"]): r["ate_m"] for r in rows if r["variant"] == "dead_reckoning"}
    summary = {}
    for v in variants:
        mine = [r for r in rows if r["variant"] == v]
        whole = [r["ate_m"] for r in mine if r["start"] == 0]
        summary[v] = {
            "mean_ate_m_whole_runs": float(np.mean(whole)),
            "mean_ate_m_all_runs": float(np.mean([r["ate_m"] for r in mine])),
            "median_ate_m_all_runs": float(np.median([r["ate_m"] for r in mine])),
            "runs_worse_than_dead_reckoning": sum(
                r["ate_m"] > drift[(r["robot"], r["start"])] for r in mine
            ),
            "ate_m": {f"r{r['robot']}@{r['start']}": round(r["ate_m"], 3) for r in mine},
            "cpu_s": float(sum(r.get("cpu_s", 0.0) for r in mine)),
        }
        log.info(
            "%-28s whole runs %.3f m, all %d runs mean %.3f / median %.3f m, %d worse than DR",
            v,
            summary[v]["mean_ate_m_whole_runs"],
            len(mine),
            summary[v]["mean_ate_m_all_runs"],
            summary[v]["median_ate_m_all_runs"],
            summary[v]["runs_worse_than_dead_reckoning"],
        )
    args.out.mkdir(parents=True, exist_ok=True)
    doc = {
        "summary": summary,
        "rows": rows,
        "variants": {v: VARIANTS[v] for v in variants},
        "protocol": {"robots": robots, "starts": starts},
        "machine": machine_info(),
    }
    (args.out / "window_study.json").write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
