"""What MRCLAM-6's sensors say against its ground truth, and whether a calibration would
move the map robot 1 builds.

1. Bearings: every labelled bearing of each robot's frames (`mrclam_frames`: the
   bearings its map gets) against the bearing from the ground-truth pose at the frame's
   stamp (`interpolate`) to the surveyed landmark. Residuals beyond 10 deg
   are counted apart (misread codes: robot 5 reads landmark 8 as 18 for frames on end);
   of the rest: mean, RMS, the mean per landmark, a fit of the residual to a constant
   plus a slope in the ground truth's turn rate (a clock offset between the two), and
   the shift of the measurements' stamps (-0.5..0.5 s in 0.05 s steps) that minimises
   the RMS.
2. Odometry: over 1 s windows, the motion the odometry integrates (`integrate_unicycle`)
   against the ground truth's: distance (windows where the truth moved more than 5 cm)
   and turn (absolute values summed), the odometry's scale. And its lag: the delay
   (-0.1..0.5 s in 0.05 s steps) of the odometry's stamps that brings its turn over
   0.25 s windows closest to the truth's (RMS of the difference). MRCLAM's odometry is
   the commanded velocity; a robot follows a command a moment later.
3. The mapper's map (`bench.localisation.build_online_map`: robot 1's whole run through
   `MapSession` with a REST client's default config, its landmarks fitted to the survey)
   as recorded, and again with robot 1's odometry divided by the scales of 2 (distance,
   turn, both): each landmark's distance from its surveyed position after the fit. If a
   calibration of the odometry were what the map lacked, the oracle's scales would
   bring the landmarks closer.
4. What each robot's data give a map, landmarks fitted to the survey (`fit_landmarks`):
   its bearings (inliers of 1) triangulated from its ground-truth poses
   (`graph.triangulation.triangulate`: the bearings alone, the poses known), and the
   batch Levenberg-Marquardt solution of its whole run (`bench.batch.batch_solve`, the
   map's factors and noise model, the REST default), started from dead reckoning and
   from the ground truth: the most likely map of its bearings and odometry together.
   The batch again with the odometry delayed by its best delay of 2.
   A landmark the first puts right and the second puts off is off because of how the
   robot's odometry and bearings combine, not because of a bearing. Beside the rigid
   fit's error, the scale of the best similarity fit (above 1: the map is too small).

    python -m bench.mrclam_sensors [--robots 1 2 3 4 5] [--mapper 1] [--out bench/results]

Writes ``<out>/mrclam_sensors.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.batch import batch_solve
from bench.localisation import build_online_map, rest_config
from graph.angles import wrap_angles
from graph.triangulation import triangulate
from graph.types import FrameInput
from service.offline.datasets.mrclam import (
    MrclamRobot,
    default_mrclam_dir,
    integrate_unicycle,
    load_mrclam,
    mrclam_frames,
    relative_motion,
    surveyed_landmarks,
)
from service.offline.evaluation import Trajectory, fit_landmarks, interpolate
from service.pipeline.config import slam_config

INLIER_RAD = math.radians(10.0)
"""A bearing within this of the one to its surveyed landmark from the true pose."""


def _truth_at(truth: Trajectory, stamps: np.ndarray) -> np.ndarray:
    """(N, 3) ground-truth poses at `stamps`, held at the ends of its span."""
    _, at = interpolate(truth, np.clip(stamps, truth.stamps[0], truth.stamps[-1]))
    return np.column_stack([at.xy, at.theta])


def _bearings(frames: list[FrameInput]) -> tuple[np.ndarray, ...]:
    """Every labelled bearing of `frames`: stamps, labels, bearings and sigmas (N,)."""
    seen = [(f.stamp, o.label, o.bearing_rad, o.sigma_rad) for f in frames for o in f.observations]
    stamps, labels, bearings, sigmas = zip(*seen, strict=True)
    return np.array(stamps), np.array(labels), np.array(bearings), np.array(sigmas, dtype=float)


def _residuals(
    pose: np.ndarray, labels: np.ndarray, bearings: np.ndarray, survey: dict[str, np.ndarray]
) -> np.ndarray:
    """Each bearing less the one from `pose` (N, 3) to its surveyed landmark, radians."""
    d = np.array([survey[label] for label in labels]) - pose[:, :2]
    return wrap_angles(bearings - (np.arctan2(d[:, 1], d[:, 0]) - pose[:, 2]))


def bearing_residuals(
    frames: list[FrameInput], truth: Trajectory, survey: dict[str, np.ndarray]
) -> dict[str, Any]:
    """Section 1 for one robot's frames (the bearings as its map gets them)."""
    stamps, labels, bearings, _ = _bearings(frames)

    def residual(shift_s: float) -> np.ndarray:
        return _residuals(_truth_at(truth, stamps + shift_s), labels, bearings, survey)

    r = residual(0.0)
    inlier = np.abs(r) <= INLIER_RAD
    r, stamps, labels, bearings = r[inlier], stamps[inlier], labels[inlier], bearings[inlier]
    rate = wrap_angles(np.diff(truth.theta)) / np.maximum(np.diff(truth.stamps), 1e-3)
    turn_rate = np.interp(stamps, truth.stamps[:-1], rate)
    constant, slope = np.linalg.lstsq(np.column_stack([np.ones_like(r), turn_rate]), r,
                                      rcond=None)[0]  # fmt: skip
    shifts = np.round(np.arange(-0.5, 0.501, 0.05), 2)
    rms = [float(np.sqrt(np.mean(residual(s) ** 2))) for s in shifts]
    best = int(np.argmin(rms))
    return {
        "measurements": len(r),
        "beyond_10_deg": int((~inlier).sum()),
        "mean_deg": math.degrees(float(np.mean(r))),
        "rms_deg": math.degrees(float(np.sqrt(np.mean(r**2)))),
        "mean_deg_by_landmark": {
            label: math.degrees(float(np.mean(r[labels == label])))
            for label in sorted(set(labels.tolist()), key=int)
        },
        "fit_constant_deg": math.degrees(float(constant)),
        "fit_seconds_per_turn_rate": float(slope),
        "best_stamp_shift_s": float(shifts[best]),
        "rms_deg_at_best_shift": math.degrees(rms[best]),
    }


def _steps(data: MrclamRobot, truth: Trajectory, step_s: float) -> np.ndarray:
    """Stamps `step_s` apart over the span both the odometry and the truth cover (1 s in
    from either end)."""
    odo = data.odometry
    start, end = max(truth.stamps[0], odo[0, 0]) + 1.0, min(truth.stamps[-1], odo[-1, 0]) - 1.0
    return np.arange(start, end, step_s)


def odometry_scale(data: MrclamRobot, truth: Trajectory) -> dict[str, float]:
    """Section 2 for one robot."""
    stamps = _steps(data, truth, 1.0)
    true_step = relative_motion(_truth_at(truth, stamps))
    odo_step = relative_motion(integrate_unicycle(data.odometry, stamps))
    moved, odo_moved = np.hypot(*true_step[:, :2].T), np.hypot(*odo_step[:, :2].T)
    turned, odo_turned = np.abs(true_step[:, 2]), np.abs(odo_step[:, 2])
    moving = moved > 0.05
    return {
        "distance_m": float(moved.sum()),
        "distance_scale": float(odo_moved[moving].sum() / moved[moving].sum()),
        "turn_rad": float(turned.sum()),
        "turn_scale": float(odo_turned.sum() / turned.sum()),
    }


def odometry_lag(data: MrclamRobot, truth: Trajectory) -> dict[str, Any]:
    """Section 2, the delay of the odometry that fits the truth best, for one robot."""
    odo, stamps = data.odometry, _steps(data, truth, 0.25)
    true_turn = relative_motion(_truth_at(truth, stamps))[:, 2]
    lags = np.round(np.arange(-0.1, 0.501, 0.05), 2)
    rms = [
        math.degrees(float(np.sqrt(np.mean(wrap_angles(
            relative_motion(integrate_unicycle(odo, stamps - lag))[:, 2] - true_turn) ** 2))))
        for lag in lags
    ]  # fmt: skip
    best = int(np.argmin(rms))
    return {
        "turn_error_rms_deg_per_0_25_s": rms[int(np.flatnonzero(lags == 0.0)[0])],
        "best_delay_s": float(lags[best]),
        "turn_error_rms_deg_at_best_delay": rms[best],
    }


def _rescaled(distance: float, turn: float) -> Any:
    def transform(data: MrclamRobot) -> MrclamRobot:
        odo = data.odometry.copy()
        odo[:, 1] /= distance
        odo[:, 2] /= turn
        return dataclasses.replace(data, odometry=odo)

    return transform


def mapper_maps(directory: Path, mapper: int, scale: dict[str, float]) -> dict[str, Any]:
    """Section 3: the mapper's map as recorded and with its odometry rescaled."""
    variants = {
        "recorded": (1.0, 1.0),
        "distance_rescaled": (scale["distance_scale"], 1.0),
        "turn_rescaled": (1.0, scale["turn_scale"]),
        "both_rescaled": (scale["distance_scale"], scale["turn_scale"]),
    }
    out: dict[str, Any] = {}
    for name, (distance, turn) in variants.items():
        with tempfile.TemporaryDirectory() as tmp:
            built = build_online_map(directory, mapper, Path(tmp) / "map.sqlite", rest_config(),
                                     transform=_rescaled(distance, turn))  # fmt: skip
        errors = built["landmark_error_in_map_frame_m"]
        by_label = sorted(errors.items(), key=lambda kv: int(kv[0]))
        out[name] = {
            "odometry_divided_by": [distance, turn],
            "landmark_rmse_in_map_frame_m": built["landmark_rmse_in_map_frame_m"],
            "frame_rotation_deg": built["frame_rotation_deg"],
            "landmark_error_in_map_frame_m": dict(by_label),
        }
    return out


def _fitted(landmarks: dict[str, Any], survey: dict[str, np.ndarray]) -> dict[str, Any]:
    fit = fit_landmarks(landmarks, survey)
    return {
        "landmarks": len(fit.labels),
        "rmse_aligned_m": fit.rmse_aligned_m,
        "similarity_scale": fit.scale,
        "error_aligned_m": fit.errors_by_label(),
    }


def data_maps(
    frames: list[FrameInput],
    delayed: list[FrameInput],
    truth: Trajectory,
    survey: dict[str, np.ndarray],
) -> dict[str, Any]:
    """Section 4 for one robot's frames (`delayed`: the same with the odometry delayed by
    its best delay of section 2)."""
    stamps, labels, bearings, sigmas = _bearings(frames)
    pose = _truth_at(truth, stamps)
    inlier = np.abs(_residuals(pose, labels, bearings, survey)) <= INLIER_RAD
    triangulated: dict[str, Any] = {}
    for label in set(labels[inlier].tolist()):
        ray = inlier & (labels == label)
        tri = triangulate(pose[ray, :2], pose[ray, 2] + bearings[ray], sigmas[ray])
        if tri is not None:
            triangulated[label] = tri.point
    config = slam_config(rest_config(), "mapping")

    def batch(run: list[FrameInput]) -> dict[str, Any]:
        _, at = interpolate(truth, np.array([f.stamp for f in run]))
        solved = batch_solve(run, config, online={"truth": at})
        return {
            name.removeprefix("online_"): {"cost": r.cost, **_fitted(r.landmark_xy, survey)}
            for name, r in solved.per_start.items()
        }

    return {
        "triangulated_from_true_poses": _fitted(triangulated, survey),
        "batch": batch(frames),
        "batch_odometry_delayed": batch(delayed),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, nargs="*", default=[1, 2, 3, 4, 5])
    parser.add_argument("--mapper", type=int, default=1)
    parser.add_argument("--data", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    args = parser.parse_args()
    directory = args.data or default_mrclam_dir()
    survey = surveyed_landmarks(directory)
    t0 = time.perf_counter()
    result: dict[str, Any] = {"command": "python -m bench.mrclam_sensors", "robots": {}}
    for robot in args.robots:
        data = load_mrclam(directory, robot)
        frames, truth = mrclam_frames(data)
        lag = odometry_lag(data, truth)
        late = data.odometry.copy()
        late[:, 0] += lag["best_delay_s"]
        delayed, _ = mrclam_frames(dataclasses.replace(data, odometry=late))
        result["robots"][str(robot)] = {
            "bearings": bearing_residuals(frames, truth, survey),
            "odometry": odometry_scale(data, truth),
            "odometry_lag": lag,
            "maps": data_maps(frames, delayed, truth, survey),
        }
    if str(args.mapper) in result["robots"]:
        scale = result["robots"][str(args.mapper)]["odometry"]
    else:
        mapper = load_mrclam(directory, args.mapper)
        scale = odometry_scale(mapper, mrclam_frames(mapper)[1])
    result["mapper"] = args.mapper
    result["mapper_maps"] = mapper_maps(directory, args.mapper, scale)
    result["seconds"] = round(time.perf_counter() - t0, 1)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "mrclam_sensors.json").write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
