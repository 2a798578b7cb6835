"""Map quality on UTIAS MRCLAM dataset 6, bearing-only, robots 1-5, each robot alone.

Every method is judged as a map's user sees it, with the losses kept apart:

- ``ate_m``: trajectory error in the map's own frame (the frame of the initial pose
  the robot gave), and ``ate_aligned_m`` after the best rigid motion onto ground truth
  (the trajectory's shape);
- the map's landmarks against their surveyed positions (service.offline.evaluation.MapFit):
  where the map frame went (``rotation_deg``, ``shift_m``) and the landmarks' RMS error
  unaligned (``rmse_m``) and after the best rigid fit (``rmse_aligned_m``). A capped map
  is judged on every landmark it has met: a live one at its estimate, a removed one at
  its last estimate.

Methods: dead reckoning; a full batch Levenberg-Marquardt over every frame (the
reference: every pose, every ray, no bound); covslam with every pose kept; covslam's
default bounded graph, uncapped; covslam at a cap of 8 landmarks for each policy
(``--seeds`` seeds for the ones that draw random numbers). Odometry noise: the model a
REST client gets when its frames carry no sigmas (``--noise default``), or MRCLAM's
own heading drift (``--noise mrclam``).

    python -m bench.mrclam_accuracy [--seeds 3] [--jobs 2] [--noise default] [--out DIR]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import platform
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import gtsam
import numpy as np

from bench.batch import batch_solve
from graph.config import SlamConfig
from graph.policies import POLICY_NAMES
from service.offline.datasets.mrclam import (
    default_mrclam_dir,
    load_mrclam,
    mrclam_frames,
    mrclam_noise,
    surveyed_landmarks,
)
from service.offline.evaluation import Trajectory, ate_rmse, dead_reckoning, fit_landmarks
from service.offline.replay import ReplayResult, replay

CAP = 8
STOCHASTIC = ("coverage", "coverage_paper", "random")
"""Policies that draw random numbers (k-means seeding, the draw itself)."""
UNCAPPED = ("dead_reckoning", "batch_lm", "every_pose", "uncapped_bounded")
UNCAPPED_CONFIG: dict[str, dict[str, Any]] = {
    "every_pose": {"pose_window": None},
    "uncapped_bounded": {},
}


def _noise(name: str) -> dict[str, Any]:
    return mrclam_noise() if name == "mrclam" else {}


def _judge(
    traj: Trajectory,
    gt: Trajectory,
    landmarks: dict[str, Any],
    surveyed: dict[str, Any],
    live: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The figures of one run; `live`: the landmarks in the graph at the end, when they
    are not all of `landmarks` (a capped map), judged on their own too."""
    row: dict[str, Any] = {
        "ate_m": ate_rmse(traj, gt),
        "ate_aligned_m": ate_rmse(traj, gt, align=True),
    }
    if len(set(landmarks) & set(surveyed)) >= 2:
        row.update(fit_landmarks(landmarks, surveyed).as_dict())
    if live is not None and len(set(live) & set(surveyed)) >= 2:
        fit = fit_landmarks(live, surveyed)
        row.update(
            live_rmse_m=fit.rmse_m,
            live_rmse_aligned_m=fit.rmse_aligned_m,
            # Where the map a client reads (GET /landmarks: the live ones) puts its frame.
            live_rotation_deg=math.degrees(fit.rotation_rad),
            live_shift_m=fit.shift_m,
        )
    return row


def map_landmarks(res: ReplayResult) -> dict[str, Any]:
    """Every landmark the map has met, by label: live ones at their estimate, archived
    ones where the archive keeps them (what `GET /landmarks?state=archived` shows)."""
    out: dict[str, Any] = {}
    for entry in res.slam.archive:  # every removed landmark that is not live again
        out[entry.label] = entry.position
    for lid, rec in res.slam.landmarks.items():
        out[rec.label] = res.slam.landmark_position(lid)
    return out


def _frames(directory: Path, robot: int, limit: int | None) -> tuple[list[Any], Trajectory]:
    frames, gt = mrclam_frames(load_mrclam(directory, robot))
    return (frames[:limit] if limit else frames), gt


def run_uncapped(
    robot: int,
    noise: str,
    directory: Path,
    limit: int | None = None,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Dead reckoning, covslam uncapped (every pose; bounded), and the batch reference.
    `extra`: estimator settings for covslam's two uncapped maps (each method's own
    settings, e.g. every pose's window, take precedence)."""
    frames, gt = _frames(directory, robot, limit)
    surveyed = surveyed_landmarks(directory)
    name = f"r{robot}"
    out: dict[str, Any] = {"dead_reckoning": _judge(dead_reckoning(frames), gt, {}, surveyed)}
    online: dict[str, Trajectory] = {}
    for method, method_extra in UNCAPPED_CONFIG.items():
        t = time.perf_counter()
        cfg = SlamConfig(landmark_cap=None, **_noise(noise), **{**(extra or {}), **method_extra})
        res = replay(frames, config=cfg, progress=False)
        online[method] = res.trajectory(name)
        out[method] = _judge(online[method], gt, map_landmarks(res), surveyed)
        out[method]["median_ms"] = float(np.median(res.frame_ms))
        out[method]["seconds"] = time.perf_counter() - t
    batch = batch_solve(frames, SlamConfig(**_noise(noise)), online=online)
    out["batch_lm"] = _judge(batch.trajectory, gt, dict(batch.landmark_xy), surveyed)
    out["batch_lm"]["start"] = batch.start
    out["frames"] = len(frames)
    return out


def run_capped(
    robot: int,
    policy: str,
    seed: int,
    noise: str,
    directory: Path,
    limit: int | None = None,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    frames, gt = _frames(directory, robot, limit)
    surveyed = surveyed_landmarks(directory)
    t = time.perf_counter()
    cfg = SlamConfig(landmark_cap=CAP, policy=policy, **_noise(noise), **(extra or {}))
    res = replay(frames, config=cfg, seed=seed, progress=False)
    live = {rec.label: res.slam.landmark_position(i) for i, rec in res.slam.landmarks.items()}
    row = _judge(res.trajectory(f"r{robot}"), gt, map_landmarks(res), surveyed, live)
    row.update(
        seed=seed,
        removals=res.slam.removal_count,
        median_ms=float(np.median(res.frame_ms)),
        seconds=time.perf_counter() - t,
    )
    return row


MEASURES = (
    "ate_m",
    "ate_aligned_m",
    "rmse_m",
    "rmse_aligned_m",
    "rotation_deg",
    "shift_m",
    "live_rmse_m",
    "live_rmse_aligned_m",
    "live_rotation_deg",
    "live_shift_m",
)


def _median_runs(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Per measure, the median over seeds (runs kept beside it)."""
    out: dict[str, Any] = {
        m: float(np.median([r[m] for r in runs])) for m in MEASURES if m in runs[0]
    }
    out["runs"] = runs
    return out


def summarise(rows: dict[str, dict[str, Any]], policies: list[str]) -> dict[str, Any]:
    """Means over robots, and the per-robot ratios to the batch the goals are read on."""
    methods = [*UNCAPPED, *(f"cap{CAP}_{p}" for p in policies)]
    mean = {
        m: {
            k: float(np.nanmean([r[m].get(k, np.nan) for r in rows.values()]))
            for k in MEASURES
            if any(k in r[m] for r in rows.values())
        }
        for m in methods
        if all(m in r for r in rows.values())
    }

    def ratios(method: str, measure: str) -> dict[str, float]:
        return {
            robot: r[method][measure] / r["batch_lm"][measure]
            for robot, r in rows.items()
            if measure in r.get(method, {}) and measure in r["batch_lm"]
        }

    out: dict[str, Any] = {"mean": mean, "ratio_to_batch": {}}
    for method in methods[2:]:
        out["ratio_to_batch"][method] = {
            measure: ratios(method, measure) for measure in ("ate_m", "ate_aligned_m", "rmse_m")
        }
    cov = f"cap{CAP}_coverage"
    baselines = [p for p in policies if not p.startswith("coverage")]
    if cov in mean and baselines:
        base = {
            robot: float(np.mean([r[f"cap{CAP}_{p}"]["ate_m"] for p in baselines]))
            for robot, r in rows.items()
        }
        out["coverage_over_baseline_mean_per_robot"] = {
            robot: r[cov]["ate_m"] / base[robot] for robot, r in rows.items()
        }
        out["coverage_over_baseline_mean"] = float(
            np.mean(list(out["coverage_over_baseline_mean_per_robot"].values()))
        )
    return out


def plot(rows: dict[str, dict[str, Any]], methods: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.5))
    width = 0.8 / len(rows)
    for ax, measure in zip(axes, ("ate_m", "ate_aligned_m", "rmse_m"), strict=True):
        for i, (robot, row) in enumerate(rows.items()):
            ax.bar(
                np.arange(len(methods)) + i * width,
                [row[m].get(measure, np.nan) for m in methods],
                width,
                label=robot,
            )
        ax.set_xticks(np.arange(len(methods)) + 0.4 - width / 2)
        ax.set_xticklabels(methods, rotation=40, ha="right", fontsize=8)
        ax.set_yscale("log")
        ax.set_title(measure)
    axes[0].legend()
    fig.suptitle("MRCLAM-6 bearing-only, each robot alone")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=3, help="seeds for stochastic policies")
    parser.add_argument("--robots", default="1,2,3,4,5")
    parser.add_argument("--policies", default=",".join(POLICY_NAMES))
    parser.add_argument("--noise", choices=("default", "mrclam"), default="default")
    parser.add_argument("--data", type=Path, default=default_mrclam_dir())
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    parser.add_argument("--name", default="mrclam_accuracy", help="file name of the results")
    parser.add_argument("--jobs", type=int, default=2, help="replays run in parallel")
    parser.add_argument("--frames", type=int, default=None, help="first N frames only (smoke)")
    parser.add_argument(
        "--capped-config",
        type=json.loads,
        default={},
        help="estimator settings for the capped maps, as JSON (e.g. '{\"spare_observed\": true}')",
    )
    parser.add_argument(
        "--uncapped-config",
        type=json.loads,
        default={},
        help="estimator settings for covslam's uncapped maps (every pose kept, bounded), as "
        'JSON (e.g. \'{"upkeep": "after_frame"}\'), to judge a setting on them too',
    )
    parser.add_argument(
        "--capped-from",
        type=Path,
        default=None,
        help="take the rows of the capped policies not in --policies from an earlier run's "
        ".rows.json (when only those policies' code changed); the summary covers them all",
    )
    parser.add_argument(
        "--uncapped-from",
        type=Path,
        default=None,
        help="take the uncapped methods' rows from an earlier run's .rows.json (when only "
        "the capped maps' code changed) instead of running them",
    )
    args = parser.parse_args()
    if not args.data.is_dir():
        raise SystemExit(f"MRCLAM data not found at {args.data} (set COVSLAM_DATA)")
    robots = [int(r) for r in args.robots.split(",")]
    policies = [p for p in args.policies.split(",") if p]
    args.out.mkdir(parents=True, exist_ok=True)
    rows: dict[str, dict[str, Any]] = {f"r{r}": {} for r in robots}
    capped: dict[tuple[str, str], list[dict[str, Any]]] = {}
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        futures: dict[Any, tuple[str, str | None]] = {}
        if args.uncapped_from is not None:
            earlier = json.loads(args.uncapped_from.read_text())
            for r in robots:
                rows[f"r{r}"].update(
                    {k: v for k, v in earlier[f"r{r}"].items() if not k.startswith("cap")}
                )
        else:
            for r in robots:
                job = pool.submit(
                    run_uncapped, r, args.noise, args.data, args.frames, args.uncapped_config
                )
                futures[job] = (f"r{r}", None)
        for r in robots:
            for p in policies:
                for seed in range(args.seeds if p in STOCHASTIC else 1):
                    job = pool.submit(
                        run_capped,
                        *(r, p, seed, args.noise, args.data, args.frames),
                        extra=args.capped_config,
                    )
                    futures[job] = (f"r{r}", p)
        for future in as_completed(futures):
            robot, policy = futures[future]
            if policy is None:
                rows[robot].update(future.result())
                print(f"{robot} uncapped: " + _line(rows[robot], UNCAPPED), flush=True)
            else:
                runs = capped.setdefault((robot, policy), [])
                runs.append(future.result())
                rows[robot][f"cap{CAP}_{policy}"] = _median_runs(runs)
            # Every finished run is on disk at once: a long run interrupted keeps its figures.
            (args.out / f"{args.name}.rows.json").write_text(json.dumps(rows, indent=1))
    seconds = time.perf_counter() - t0
    if args.capped_from is not None:
        earlier = json.loads(args.capped_from.read_text())
        earlier = earlier.get("rows", earlier)  # a results file, or its .rows.json
        for robot in rows:
            kept = {k: v for k, v in earlier[robot].items() if k.startswith(f"cap{CAP}_")}
            rows[robot].update({k: v for k, v in kept.items() if k not in rows[robot]})
        reused = {k[len(f"cap{CAP}_") :] for r in rows.values() for k in r if k.startswith("cap")}
        policies = [*policies, *sorted(reused - set(policies))]
    methods = [*UNCAPPED, *(f"cap{CAP}_{p}" for p in policies)]
    for robot, row in rows.items():
        print(f"{robot} cap {CAP}: " + _line(row, methods[len(UNCAPPED) :]))
    summary = summarise(rows, policies)
    doc = {
        "rows": rows,
        "summary": summary,
        "protocol": {
            "robots": robots,
            "seeds": args.seeds,
            "policies": policies,
            "capped_rows_reused_from": None if args.capped_from is None else str(args.capped_from),
            "capped_config": args.capped_config,
            "uncapped_config": args.uncapped_config,
            "noise": args.noise,
            "cap": CAP,
            "jobs": args.jobs,
            "seconds": seconds,
            "uncapped_from": None if args.uncapped_from is None else str(args.uncapped_from),
        },
        "machine": {
            "cpus": os.cpu_count(),
            "loadavg_at_end": os.getloadavg(),
            "platform": platform.platform(),
            "gtsam": getattr(gtsam, "__version__", "?"),
            "numpy": np.__version__,
            "date": dt.date.today().isoformat(),
        },
    }
    (args.out / f"{args.name}.json").write_text(json.dumps(doc, indent=1))
    plot(rows, methods, args.out / f"{args.name}.png")
    print(json.dumps(summary["mean"], indent=1))


def _line(row: dict[str, Any], methods: list[str] | tuple[str, ...]) -> str:
    parts = []
    for m in methods:
        r = row.get(m)
        if r is None:
            continue
        lm = f" lm {r['rmse_m']:.3f}/{r['rmse_aligned_m']:.3f}" if "rmse_m" in r else ""
        rot = f" {r['rotation_deg']:+.1f}deg" if "rotation_deg" in r else ""
        parts.append(f"{m} {r['ate_m']:.3f}/{r['ate_aligned_m']:.3f}{lm}{rot}")
    return "  ".join(parts)


if __name__ == "__main__":
    main()
