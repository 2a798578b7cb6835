"""What limits a capped map on MRCLAM-6: the estimator, or the data the cap leaves it?

For each robot, one online run at a landmark cap (default: 8, `coverage`) is replayed,
and its data association is read back frame by frame: the live landmark that held each
observation's label after the frame, or, for an observation no live landmark held, the
next landmark of that label to appear within `--ray-frames` frames (its candidate's rays;
a landmark added and removed in one frame appears through the removal log). Every
online landmark id becomes its own label, so a landmark removed and seen again is a
second landmark, as in the online map; observations no landmark took are dropped.

Full batch Levenberg-Marquardt (bench.batch) then solves:

- ``batch_all``: every observation (the accuracy reference of bench.mrclam_accuracy);
- ``batch_same_data``: the online run's association (starts: dead reckoning, the online
  estimate and batch_all's solution; the lowest graph error wins);
- ``batch_fixed_subset``: a fixed random subset of `cap` of the robot's landmark labels
  kept for the whole run (median over `--subsets` subsets; starts: dead reckoning and
  batch_all's solution), the reference the cap-8 accuracy goal was set against;
- ``batch_fixed_subset_dr_start``: the same subsets from dead reckoning alone (no
  start that has seen every landmark, which no online map has).

And online, on the same fixed subsets (no landmark is ever removed, so no churn):

- ``online_fixed_subset``: the capped configuration itself (its 100-pose window);
- ``online_fixed_subset_every_pose``: the same with every pose kept.

If batch_same_data is as far off as the online run, a better estimator cannot close the
gap; only the association (which landmarks live when) can. If the online runs on a fixed
subset are far off as well, the association is not the only loss: the incremental
estimator on so few landmarks is one too.

The association is an approximation where candidate rays are concerned (rays a
candidate dropped with poses that left the window, or observations refused by the
innovation gate, count as used).

    python -m bench.cap_data_study [--robots 1,2,3,4,5] [--cap 8] [--policy coverage]
                                   [--jobs 2] [--out bench/results]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np

from bench.batch import batch_solve
from bench.lifelong import machine_info
from bench.mrclam_cli import mrclam_parser, parse_mrclam
from graph.config import SlamConfig
from graph.slam import BearingSlam, RemovalRecord
from graph.types import FrameInput
from service.offline.datasets.mrclam import (
    load_mrclam,
    mrclam_frames,
    mrclam_noise,
)
from service.offline.evaluation import Trajectory, ate_rmse
from service.offline.replay import ReplayResult, replay

log = logging.getLogger("bench.cap_data_study")

FIXED_SUBSET_KEYS = (
    "batch_fixed_subset",
    "batch_fixed_subset_dr_start",
    "online_fixed_subset",
    "online_fixed_subset_every_pose",
)
"""The columns measured on the fixed subsets (each the median over the subsets)."""


def online_association(
    frames: list[FrameInput], config: SlamConfig, seed: int, ray_frames: int
) -> tuple[Trajectory, list[FrameInput], dict[str, int]]:
    """The online run's trajectory and its frames relabelled by online landmark id."""
    appeared: dict[int, tuple[int, str]] = {}

    def removed(record: RemovalRecord) -> None:  # also a landmark added and removed at once
        appeared.setdefault(record.landmark_id, (record.frame, record.label))

    slam = BearingSlam(config, rng=np.random.default_rng(seed), removal_sink=removed)
    held: list[list[int | None]] = []
    for k, frame in enumerate(frames):
        slam.process(frame)
        live = {record.label: lid for lid, record in slam.landmarks.items()}
        for label, lid in live.items():
            appeared.setdefault(lid, (k, label))
        held.append([live.get(o.label) for o in frame.observations])
    by_label: dict[str, list[tuple[int, int]]] = {}
    for lid, (k, label) in appeared.items():
        by_label.setdefault(label, []).append((k, lid))
    for ids in by_label.values():
        ids.sort()
    out, used = [], 0
    for k, frame in enumerate(frames):
        kept = []
        for obs, holder in zip(frame.observations, held[k], strict=True):
            if holder is None:
                later = [i for f, i in by_label.get(obs.label, []) if k <= f <= k + ray_frames]
                holder = later[0] if later else None
            if holder is not None:
                kept.append(dataclasses.replace(obs, label=f"{obs.label}#{holder}"))
        used += len(kept)
        out.append(dataclasses.replace(frame, observations=tuple(kept)))
    counts = {
        "landmark_ids": len(appeared),
        "removals": slam.removal_count,
        "observations": sum(len(f.observations) for f in frames),
        "observations_used": used,
    }
    return ReplayResult(slam).trajectory(frames[0].robot), out, counts


def _only(frames: list[FrameInput], labels: set[str]) -> list[FrameInput]:
    return [
        dataclasses.replace(f, observations=tuple(o for o in f.observations if o.label in labels))
        for f in frames
    ]


def run_robot(robot: int, args: argparse.Namespace) -> dict[str, Any]:
    frames, gt = mrclam_frames(load_mrclam(args.data, robot))
    noise = mrclam_noise()
    config = SlamConfig(landmark_cap=args.cap, policy=args.policy, **noise)
    online, relabelled, counts = online_association(frames, config, args.seed, args.ray_frames)
    reference = SlamConfig(**noise)
    full = batch_solve(frames, reference, online=online)
    same = batch_solve(
        relabelled, reference, online={"online": online, "batch_all": full.trajectory}
    )
    labels = sorted({o.label for f in frames for o in f.observations})
    rng = np.random.default_rng(args.seed)
    runs: dict[str, list[float]] = {k: [] for k in FIXED_SUBSET_KEYS}
    name = frames[0].robot
    for _ in range(args.subsets):
        chosen = set(rng.choice(labels, size=min(args.cap, len(labels)), replace=False))
        only = _only(frames, chosen)
        fixed = batch_solve(only, reference, online=full.trajectory)
        runs["batch_fixed_subset"].append(ate_rmse(fixed.trajectory, gt))
        if "dead_reckoning" not in fixed.per_start:
            raise RuntimeError(f"r{robot}: batch LM from dead reckoning failed on {chosen}")
        from_dr = fixed.per_start["dead_reckoning"].trajectory
        runs["batch_fixed_subset_dr_start"].append(ate_rmse(from_dr, gt))
        for key, online_config in (
            ("online_fixed_subset", config),
            ("online_fixed_subset_every_pose", dataclasses.replace(config, pose_window=None)),
        ):
            res = replay(only, config=online_config, seed=args.seed, progress=False)
            runs[key].append(ate_rmse(res.trajectory(name), gt))
    row = {
        "robot": robot,
        "online": ate_rmse(online, gt),
        "batch_all": ate_rmse(full.trajectory, gt),
        "batch_same_data": ate_rmse(same.trajectory, gt),
        "batch_same_data_start": same.start,
        **{k: float(np.median(v)) for k, v in runs.items()},
        **{f"{k}_runs": v for k, v in runs.items()},
        **counts,
    }
    log.info("%s", {k: round(v, 3) if isinstance(v, float) else v for k, v in row.items()})
    return row


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = mrclam_parser(__doc__)
    parser.add_argument("--cap", type=int, default=8)
    parser.add_argument("--policy", default="coverage")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--subsets", type=int, default=3, help="random fixed subsets per robot")
    parser.add_argument("--ray-frames", type=int, default=150)
    args, robots = parse_mrclam(parser)
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        rows = list(pool.map(run_robot, robots, [args] * len(robots)))
    keys = ("online", "batch_all", "batch_same_data", *FIXED_SUBSET_KEYS)
    mean = {k: float(np.mean([r[k] for r in rows])) for k in keys}
    summary = {
        "mean_ate_m": mean,
        "ratio_to_batch_all": {k: mean[k] / mean["batch_all"] for k in keys},
    }
    log.info("%s", json.dumps(summary, indent=1))
    args.out.mkdir(parents=True, exist_ok=True)
    doc = {
        "summary": summary,
        "rows": rows,
        "protocol": {
            "robots": robots,
            "cap": args.cap,
            "policy": args.policy,
            "seed": args.seed,
            "subsets": args.subsets,
            "ray_frames": args.ray_frames,
        },
        "machine": machine_info(),
    }
    name = f"cap_data_study_{args.policy}_cap{args.cap}.json"
    (args.out / name).write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
