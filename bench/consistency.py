"""Are the map's landmark covariances honest? NEES against the survey on MRCLAM-6.

Each of robots 1-5 alone, bearing-only, default odometry noise: covslam uncapped
(bounded window), covslam at cap 8 (coverage policy), and the batch LM reference (every
pose, gtsam.Marginals). For every landmark the map holds at the end and the survey
knows, the normalised estimation error squared ``e^T S^-1 e`` of its estimate against
the surveyed position, in the map frame (the frame of the initial pose: the covariance
is the absolute one the service reports), S the estimator's own marginal covariance.
A consistent estimator's NEES follows chi^2 with 2 degrees of freedom: mean 2, median
1.39, 95 % below 5.99. Larger means overconfident. The survey and the bearing model
need not agree (a biased bearing, a mis-surveyed post): the batch over all the data is
the reference for what the data allows.

    python -m bench.consistency [--robots 1,2,3,4,5] [--jobs 2]
"""

from __future__ import annotations

import json
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from bench.batch import batch_solve
from bench.lifelong import machine_info
from bench.mrclam_accuracy import CAP, _frames, _noise
from bench.mrclam_cli import mrclam_parser, parse_mrclam
from graph.config import SlamConfig
from service.offline.datasets.mrclam import surveyed_landmarks
from service.offline.replay import replay

CHI2_2_95 = 5.991
"""95 % quantile of chi^2 with 2 degrees of freedom."""


def nees_figures(
    estimates: dict[str, Any], covariances: dict[str, Any], surveyed: dict[str, Any]
) -> dict[str, Any]:
    """Mean, median and share within the 95 % bound of the NEES of every landmark in
    both `estimates` and `surveyed` (by label)."""
    values = []
    for label, point in estimates.items():
        if label not in surveyed or label not in covariances:
            continue
        e = np.asarray(point, dtype=np.float64) - np.asarray(surveyed[label], dtype=np.float64)
        values.append(float(e @ np.linalg.solve(np.asarray(covariances[label]), e)))
    a = np.asarray(values)
    if not len(a):
        return {"landmarks": 0}
    return {
        "landmarks": len(a),
        "mean": float(a.mean()),
        "median": float(np.median(a)),
        "within_95": float(np.mean(a <= CHI2_2_95)),
    }


def run(robot: int, directory: Path) -> dict[str, Any]:
    frames, _ = _frames(directory, robot, None)
    surveyed = surveyed_landmarks(directory)
    out: dict[str, Any] = {}
    for name, cap in (("uncapped_bounded", None), ("cap8_coverage", CAP)):
        cfg = SlamConfig(landmark_cap=cap, policy="coverage", **_noise("default"))
        slam = replay(frames, config=cfg, progress=False).slam
        ids = list(slam.landmarks)
        cov = slam.landmark_covariances(ids)
        labels = [slam.landmarks[i].label for i in ids]
        out[name] = nees_figures(
            {lb: slam.landmark_position(i) for lb, i in zip(labels, ids, strict=True)},
            dict(zip(labels, cov, strict=True)),
            surveyed,
        )
    batch = batch_solve(frames, SlamConfig(**_noise("default")), covariances=True)
    out["batch_lm"] = nees_figures(dict(batch.landmark_xy), batch.landmark_cov, surveyed)
    return out


def main() -> None:
    args, robots = parse_mrclam(mrclam_parser(__doc__))
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        rows = dict(
            zip(
                (f"r{r}" for r in robots),
                pool.map(run, robots, [args.data] * len(robots)),
                strict=True,
            )
        )
    methods = ("uncapped_bounded", "cap8_coverage", "batch_lm")
    for name, row in rows.items():
        cells = "  ".join(
            f"{m} {row[m].get('mean', float('nan')):7.2f} ({row[m]['landmarks']})" for m in methods
        )
        print(f"{name}: mean NEES (landmarks)  {cells}")
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "consistency.json"
    path.write_text(
        json.dumps(
            {
                "rows": rows,
                "protocol": {
                    "dataset": "MRCLAM-6",
                    "robots": robots,
                    "cap": CAP,
                    "policy": "coverage",
                    "noise": "default",
                    "frame": "map (the initial pose's); no alignment",
                    "consistent": "chi^2 2 dof: mean 2, median 1.39, 95 % within 5.99",
                    "seconds": time.perf_counter() - t0,
                },
                "machine": machine_info(),
            },
            indent=1,
        )
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
