"""Why the bounded graph misses batch accuracy on MRCLAM-6: pose-window variants.

Uncapped covslam (every landmark kept) on robots 1-5, bearing-only, for: the default
bounded graph (100-pose window + keyframes), a 200-pose window, every pose kept, and
`keyframe_for_candidate_rays` (a pose holding a candidate's first ray stays as a
keyframe). Per robot: ATE RMSE, median ms per frame, and the final error of every
landmark against the surveyed map (a group of landmarks that stays off together is
the signature of information marginalised at a wrong estimate).

    python -m bench.window_study [--robots 1,2,3,4,5] [--jobs 2] [--out bench/results]
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from bench.lifelong import machine_info
from graph.config import SlamConfig
from service.datasets.mrclam import default_mrclam_dir, load_mrclam, mrclam_frames, mrclam_noise
from service.evaluation import ate_rmse
from service.replay import replay

log = logging.getLogger("bench.window_study")

VARIANTS: dict[str, dict[str, Any]] = {
    "default": {},
    "window_200": {"pose_window": 200},
    "every_pose": {"pose_window": None},
    "keyframe_for_candidate_rays": {"keyframe_for_candidate_rays": True},
}


def run(robot: int, variant: str, directory: Path) -> dict[str, Any]:
    data = load_mrclam(directory, robot)
    frames, gt = mrclam_frames(data)
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
        "robot": robot,
        "variant": variant,
        "ate_m": ate_rmse(res.trajectory(f"r{robot}"), gt),
        "median_ms": float(np.median(res.frame_ms)),
        "cpu_s": time.process_time() - t,
        "landmark_error_m": dict(sorted(errors.items(), key=lambda kv: int(kv[0]))),
    }


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--robots", default="1,2,3,4,5")
    parser.add_argument("--data", type=Path, default=default_mrclam_dir())
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args()
    if not args.data.is_dir():
        raise SystemExit(f"MRCLAM data not found at {args.data} (set COVSLAM_DATA)")
    robots = [int(r) for r in args.robots.split(",")]
    jobs = [(r, v) for v in VARIANTS for r in robots]
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        rows = list(pool.map(run, *zip(*jobs, strict=True), [args.data] * len(jobs)))
    summary = {}
    for v in VARIANTS:
        mine = [r for r in rows if r["variant"] == v]
        summary[v] = {
            "mean_ate_m": float(np.mean([r["ate_m"] for r in mine])),
            "ate_m": {f"r{r['robot']}": round(r["ate_m"], 3) for r in mine},
            "cpu_s": float(sum(r["cpu_s"] for r in mine)),
        }
        log.info("%-28s mean ATE %.3f m  %s", v, summary[v]["mean_ate_m"], summary[v]["ate_m"])
    args.out.mkdir(parents=True, exist_ok=True)
    doc = {"summary": summary, "rows": rows, "variants": VARIANTS, "machine": machine_info()}
    (args.out / "window_study.json").write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
