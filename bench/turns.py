"""On-the-spot 90-degree turns on rendered panoramas: does the camera robot keep track?

Thompson & Zelinsky's place localiser lost track when the robot turned (DESIGN.md,
"Place localiser"). Here a robot drives a staircase through the first of two rendered rooms of
`indoor_sim` (legs of `--leg-m` metres, turning 90 degrees on the spot between legs,
alternately left and right), then turns on the spot through a full circle in 90-degree
steps. Every turn happens between two consecutive frames (`--turn-frames` 1) or over a
few. Every frame is a 1024x256 panorama, posted with its odometry (noisy) to a
MapSession with a camera map: the image pipeline associates its features, the graph
estimates the pose.

Per frame: the status the frame result reports; the status of a watch filter (the
place localiser's particle filter stepped on the association's labelled observations
and the graph's pose, exactly as the service runs it on labelled frames: it goes `lost`
when the filter and the graph disagree, or the observations stop fitting the map; the
service now steps its own filter on image frames too (service.pipeline), on
the landmark matches only, so the two can differ); the position and heading error of the
reported pose; the landmarks the frame observed.

    python -m bench.turns [--turn-frames 1] [--out bench/results]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from graph.localiser import LOST
from service.offline.datasets.camera_runs import CAMERA, render_turn_run, run_turns


def plot(doc: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = doc["runs"]
    fig, axes = plt.subplots(len(runs), 1, figsize=(10, 3.2 * len(runs)), squeeze=False)
    for ax, run in zip(axes[:, 0], runs, strict=True):
        rows = run["rows"]
        seq = [r["seq"] for r in rows]
        ax.plot(seq, [r["error_m"] for r in rows], label="position error, m")
        ax.plot(seq, [r["error_deg"] / 10 for r in rows], label="heading error, deg / 10")
        for r in rows:
            if r["turning"]:
                ax.axvline(r["seq"], color="0.85", zorder=0)
            if r["watch_status"] == LOST:
                ax.axvline(r["seq"], color="r", alpha=0.4)
        ax2 = ax.twinx()
        ax2.plot(seq, [r["observed"] for r in rows], "g.", ms=3, label="landmarks observed")
        ax2.set_ylabel("landmarks observed", color="g")
        ax.set_title(
            f"90-degree turns over {run['turn_frames_per_turn']} frame(s), "
            f"odometry {run['odometry_kt']} rad/rad, compass {'on' if run['compass'] else 'off'}: "
            f"lost frames {run['lost_frames']} (watch filter {run['watch_lost_frames']})"
        )
        ax.set_xlabel("frame (grey: turn frames)")
        ax.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument(
        "--variants",
        nargs="*",
        default=["1:0.02", "3:0.02", "1:0.1", "1:0.1:off", "1:0.2"],
        help="runs as FRAMES:KT[:off]: a 90-degree turn over FRAMES frames, odometry "
        "heading sigma KT per radian turned (and per metre driven); off: without the "
        "front end's visual compass",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    args = parser.parse_args()
    doc: dict[str, Any] = {
        "when": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "load_average": [round(v, 2) for v in os.getloadavg()],
        "camera": f"panorama {CAMERA.width}x{CAMERA.height}",
        "seed": args.seed,
        "runs": [],
    }
    for variant in args.variants:
        n_text, kt_text, *rest = variant.split(":")
        n, kt, compass = int(n_text), float(kt_text), rest != ["off"]
        t0 = time.perf_counter()
        run = render_turn_run(
            rng=np.random.default_rng(args.seed), turn_frames=n, odometry_noise=(0.02, 0.02, kt)
        )
        out = {
            "turn_frames_per_turn": n,
            "odometry_kt": kt,
            "compass": compass,
            **run_turns(run, seed=args.seed, compass=compass),
        }
        out["seconds"] = time.perf_counter() - t0
        doc["runs"].append(out)
        print({k: v for k, v in out.items() if k != "rows"})
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "turns.json").write_text(json.dumps(doc, indent=1))
    plot(doc, args.out / "turns.png")


if __name__ == "__main__":
    main()
