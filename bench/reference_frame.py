"""Where an independent estimator's map frame goes on MRCLAM-6: the yardstick for
covslam's map-frame figures (bench.mrclam_accuracy).

The independent plain-iSAM2 reference (``../shared/reference/mrclam_reference.py``,
written outside the project; set ``COVSLAM_REFERENCE`` to its directory) anchors its
first pose with a prior at ground truth (1 mm, 0.006 deg) and keeps every pose. It
reports ATE after alignment only; this script runs its batch Levenberg-Marquardt (B),
its plain iSAM2 (C) and its cap of 8 with covslam's rule (``churn_marg_info``: the
least informative landmark marginalised, one seen again a new landmark) unchanged and
judges their final estimates as
bench.mrclam_accuracy judges covslam's: the landmarks fitted to the surveyed ones by
a rigid motion (its rotation, and how far it moves their centroid), ATE unaligned
(in the frame of the first pose) and aligned. The reference's own ``ate`` and
``landmark_rmse`` are wrapped to see the estimates; nothing of it is copied.

    python -m bench.reference_frame [--data DIR] [--reference DIR] [--runs batch_lm,...]
        [--out bench/results]

Writes ``<out>/reference_frame.json``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from service.offline.datasets.mrclam import default_mrclam_dir
from service.offline.evaluation import fit_landmarks

RUNS: dict[str, Callable[[Any, Any, Any], Any]] = {
    "batch_lm": lambda ref, kf, cfg: ref.run_batch(kf, cfg),
    "plain_isam2": lambda ref, kf, cfg: ref.run_isam2(kf, cfg),
    # covslam's rule without its pose bound: cap 8, the least informative landmark
    # marginalised, one seen again re-enters as a new landmark (the reference's
    # churn_marg_info).
    "cap8_marginalise_information": lambda ref, kf, cfg: ref.run_isam2_variant(
        kf, cfg, cap=8, policy="info", churn=True, removal="marginalise"
    ),
}


def default_reference_dir() -> Path:
    env = os.environ.get("COVSLAM_REFERENCE")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / "shared" / "reference"


def judge(ref: Any, directory: Path, robot: int, run: str) -> dict[str, Any]:
    """One robot through one of the reference's estimators, judged on its final
    estimate (the first call of its ``ate`` and ``landmark_rmse`` in a run)."""
    seen: dict[str, Any] = {}
    ate, landmark_rmse = ref.ate, ref.landmark_rmse

    def ate_hook(est_xy: np.ndarray, kf: Any) -> Any:
        seen.setdefault("trajectory", (np.array(est_xy), kf))
        return ate(est_xy, kf)

    def landmark_hook(lms: dict[int, Any], kf: Any, align: Any) -> Any:
        seen.setdefault("landmarks", {i: np.asarray(p, dtype=float) for i, p in lms.items()})
        return landmark_rmse(lms, kf, align)

    ref.ate, ref.landmark_rmse = ate_hook, landmark_hook
    try:
        cfg = ref.Config()
        kf = ref.build_keyframes(str(directory), robot, cfg)
        result = RUNS[run](ref, kf, cfg)
    finally:
        ref.ate, ref.landmark_rmse = ate, landmark_rmse
    if isinstance(result, dict) and "failed" in result:
        return {"failed": str(result["failed"])}
    est_xy, kf = seen["trajectory"]
    ok = kf.gt_ok
    err = est_xy[ok] - kf.gt[ok, :2]
    fit = fit_landmarks(
        {str(i): p for i, p in seen["landmarks"].items()},
        {str(i): np.asarray(kf.lm_gt[i], dtype=float) for i in seen["landmarks"]},
    )
    return {
        "ate_m": float(np.sqrt(np.mean(np.sum(err**2, axis=1)))),
        "ate_aligned_m": float(ate(est_xy, kf)[0]),
        "rotation_deg": math.degrees(fit.rotation_rad),
        "shift_m": fit.shift_m,
        "rmse_m": fit.rmse_m,
        "rmse_aligned_m": fit.rmse_aligned_m,
        "landmarks": len(fit.labels),
        "landmark_error_aligned_m": fit.errors_by_label(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=default_mrclam_dir())
    parser.add_argument("--reference", type=Path, default=default_reference_dir())
    parser.add_argument("--robots", default="1,2,3,4,5")
    parser.add_argument(
        "--runs",
        default=",".join(RUNS),
        help="which of the reference's estimators (the others keep their rows from an "
        "existing reference_frame.json)",
    )
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    args = parser.parse_args()
    if not (args.reference / "mrclam_reference.py").exists():
        raise SystemExit(f"the reference is not at {args.reference} (set COVSLAM_REFERENCE)")
    threadpool_limits(1, user_api="blas")
    sys.path.insert(0, str(args.reference))
    ref = importlib.import_module("mrclam_reference")
    path = args.out / "reference_frame.json"
    rows: dict[str, dict[str, Any]] = json.loads(path.read_text())["rows"] if path.exists() else {}
    for robot in (int(r) for r in args.robots.split(",")):
        for run in args.runs.split(","):
            row = judge(ref, args.data, robot, run)
            rows.setdefault(f"r{robot}", {})[run] = row
            figures = ", ".join(f"{k} {v:.3f}" for k, v in row.items() if isinstance(v, float))
            print(f"r{robot} {run}: {figures or row}", flush=True)
    doc = {
        "rows": rows,
        "protocol": {
            "reference": str(args.reference / "mrclam_reference.py"),
            "data": str(args.data),
            "judged": "final estimate; landmarks fitted to the surveyed ones (rigid)",
        },
    }
    args.out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
