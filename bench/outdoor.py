"""An outdoor-scale world over REST: the default map config against one for landmarks
tens of metres away, set in the map's config alone.

Run from the repository root against a running service (2 cores: never during someone
else's benchmark)::

    covslam serve --port 8000 &
    python -m bench.outdoor --url http://127.0.0.1:8000 [--seed 0] [--out bench/results]
        [--name outdoor] [--odometry-scale 1.01] [--maps default,outdoor,...]

World (service.offline.datasets.outdoor_sim.outdoor_run, seed ``--seed``, the run ``--seed + 1``): a
rounded-rectangle loop road 160 x 80 m (445 m a lap), 150 trees 5-80 m from it; 1.5
laps at 0.75 m a frame (892 frames), up to 12 bearings a frame (sigma 1 deg) to trees
within 100 m, wheel odometry with 2 % noise and a 1 % scale error. Four maps, the
first three uncapped so that the triangulation alone decides which trees become
landmarks:

``default``     ``{"landmark_cap": null}``: the estimator's defaults (max_depth_m 15,
                max_position_sigma_m 0.3);
``outdoor``     ``{"landmark_cap": null, "triangulation": OUTDOOR_TRIANGULATION}``;
``depth_only``  ``{"landmark_cap": null, "triangulation": {"max_depth_m": 100}}``;
``outdoor_default_cap`` the outdoor triangulation under the service's default cap (its
                setting default_landmark_cap, 50): what a bounded map keeps.

Per map, from the REST API (GET /v1/maps/{id}, /trajectory, /landmarks) and the frame
results: trees initialised (of those observed; distinct labels), landmark
initialisations (distinct ids: a capped map re-initialises a removed tree seen again
under a new id), ATE RMSE unaligned and SE(2)-aligned (no scale), landmark RMSE and
max error of the live landmarks (unaligned: where the map put them, against the
simulator's trees), HTTP ms a frame. Dead reckoning's ATE for reference. Writes
``<out>/<name>.json`` (by default ``bench/results/outdoor.json``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from service.offline.datasets.outdoor_sim import CONFIGS, outdoor_run
from service.offline.evaluation import ate_rmse, dead_reckoning, map_figures
from service.offline.http_client import replay_http


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--url", required=True, help="the service, e.g. http://127.0.0.1:8000")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("bench/results"))
    ap.add_argument("--name", default="outdoor", help="results file <out>/<name>.json")
    ap.add_argument(
        "--odometry-scale", type=float, default=1.01, help="odometry's distance scale error"
    )
    ap.add_argument("--maps", default=",".join(CONFIGS), help="which of " + ", ".join(CONFIGS))
    args = ap.parse_args(argv)
    run = outdoor_run(args.seed, odometry_scale=args.odometry_scale)
    dead = dead_reckoning(run.frames)
    doc: dict[str, Any] = {
        "command": "python -m bench.outdoor " + " ".join(argv or sys.argv[1:]),
        "seed": args.seed,
        "odometry_scale": args.odometry_scale,
        "frames": len(run.frames),
        "path_m": float(np.sum(np.hypot(*np.diff(run.ground_truth.xy, axis=0).T))),
        "observations_per_frame": float(np.mean([len(f.observations) for f in run.frames])),
        "dead_reckoning": {
            "ate_rmse_m": ate_rmse(dead, run.ground_truth),
            "ate_rmse_aligned_m": ate_rmse(dead, run.ground_truth, align=True),
        },
        "maps": {},
    }
    with httpx.Client(base_url=args.url.rstrip("/"), timeout=120) as client:
        for name in args.maps.split(","):
            config = CONFIGS[name]
            posted = replay_http(run.frames, url=args.url, name=f"outdoor-{name}", config=config)
            figures = map_figures(client, posted.map_id, run, posted.results)
            figures["http_ms_per_frame_p50"] = float(np.median(posted.latency_ms))
            doc["maps"][name] = figures
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.json").write_text(json.dumps(doc, indent=2) + "\n")
    sys.stdout.write(json.dumps(doc["maps"], indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
