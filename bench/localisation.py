"""The place localiser: particle-filter speed, MRCLAM-6 global localisation, kidnapping.

1. PF update time (weighting by 32 bearings, no resampling) and a full step
   (motion + weighting + resampling when due) for 1000 and 5000 particles.
2. MRCLAM dataset 6, global localisation without initial pose: from random start
   frames spread over robots 1-5, the localiser runs on the robot's frames alone.
   Its map is the surveyed landmark map (Landmark_Groundtruth: 15 landmarks) and
   places learnt along robot 1's first 300 s at ground-truth poses. Success: the
   status becomes `relocalised` within `--max-frames` frames and the estimate then
   lies within 0.5 m and 15 deg of ground truth.
3. Kidnapping: the whole service pipeline (MapSession: graph + localiser) maps with
   robot N from its initial pose; 60 s of its frames are cut out (the robot jumps,
   without odometry for the gap). Frames from the cut until `relocalised`, and the
   ATE of the reported poses afterwards.
2b. Information bound (``--parts bound``): per start of 2, the first frame at which the
   Cramer-Rao bound of the pose (odometry + labelled bearings, linearised at ground
   truth) is as tight as the filter's convergence test: no estimator can be that sure
   sooner on the same frames.
2c. Online map (``--parts online``): robot N (``--mapper``; ``--mappers 1 2 3 4 5``: each in
   turn, and a table of them) maps its whole run through the
   service as a REST client would (default config, its true initial pose); the other
   robots then enter a copy of that map without ``initial_pose`` from random frames
   (``--online-starts`` per robot and seed). Judged in the map's own frame (ground truth
   moved by the fit of the map's landmarks to the surveyed ones): success when a
   `relocalised` frame's reported pose and the next 19 lie within 0.5 m / 15 deg; a
   wrong convergence is `relocalised` reported beyond it. Beside each start, the
   information bound of 2b on the map's own landmarks, and at its first `relocalised`
   the pose the map itself implies (the frames since the start solved against the map's
   landmarks from the truth): a reported pose within tolerance of that one but not of
   the truth is the map's error there, not the localiser's. ``--online-map batch`` /
   ``surveyed``: the same with the map's estimate replaced by a batch LM solution of the
   mapper's run, or by the surveyed landmarks (MAP_SOURCES): what the mapper's data
   allow, and a control.
2d. Window check (``--parts check``): global localisation on the surveyed map with and
   without graph.window_check, per seed: wrong convergences, starts never relocalised.
3b. Online kidnap (``--parts online-kidnap``): kidnapping in the map of 2c.
4. Tracking (``--parts tracking``): each robot's whole run, no kidnap, through the same
   pipeline; every `lost` there is a false alarm.

    python -m bench.localisation [--starts 50] [--out bench/results]
        [--parts pf global check study bound online online-kidnap kidnap tracking]
        [--online-map session|batch|surveyed] [--online-seeds 0 1 2]
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import math
import os
import pickle
import platform
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import gtsam
import numpy as np

from bench.batch import batch_graph, batch_solve
from graph.angles import wrap_angle, wrap_angles
from graph.factors import is_landmark_key, landmark_key, pose_key
from graph.localiser import RELOCALISED, TRACKING, Localiser, LocaliserConfig, RobotTrack
from graph.particles import FilterConfig, ParticleFilter, motion_sigmas, predicted_bearings
from graph.slam import BearingSlam
from graph.types import FrameInput, Odometry, Pose2D
from graph.window_check import WindowCheckConfig, WindowFrame, check_window, rejects_old_pose
from service.frames_io import frame_to_dict
from service.offline.datasets.mrclam import (
    MrclamRobot,
    default_mrclam_dir,
    load_mrclam,
    mrclam_frames,
)
from service.offline.evaluation import Trajectory, align_se2, fit_landmarks, interpolate
from service.pipeline.config import DEFAULT_LANDMARK_CAP, MapConfig
from service.pipeline.localiser import (
    landmark_covariances,
    landmark_ids,
    landmark_map,
    map_localiser_config,
)
from service.pipeline.snapshot import snapshot_pipeline
from service.session import MapSession
from service.settings import StoreSettings
from service.store import MapRecord


# --------------------------------------------------------------------------- 1. speed
def pf_timing(n_particles: int, n_landmarks: int = 32, repeats: int = 300) -> dict[str, float]:
    rng = np.random.default_rng(0)
    # Weighting only: no resampling, one stage (progressive correction timed below).
    cfg = FilterConfig(
        max_particles=max(5000, n_particles), resample_ess_fraction=0.0, tempering_ess_fraction=0.0
    )
    poses = np.column_stack(
        [rng.uniform(0, 10, n_particles), rng.uniform(0, 10, n_particles),
         rng.uniform(-math.pi, math.pi, n_particles)]
    )  # fmt: skip
    landmarks = rng.uniform(-5, 15, (n_landmarks, 2))
    bearings = rng.uniform(-math.pi, math.pi, n_landmarks)
    pf = ParticleFilter.from_poses(poses, cfg)
    update = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        pf.update(landmarks, bearings, rng=rng)
        update.append(time.perf_counter() - t0)
    # A sharp observation of a spread-out set: the update runs in several stages.
    staged, stages = [], []
    for _ in range(max(repeats // 10, 5)):
        pf = ParticleFilter.from_poses(poses, FilterConfig(max_particles=max(5000, n_particles)))
        t0 = time.perf_counter()
        pf.update(landmarks, bearings, rng=rng)
        staged.append(time.perf_counter() - t0)
        stages.append(pf.last_stages)
    full_cfg = FilterConfig(max_particles=n_particles, min_particles=n_particles)
    pf = ParticleFilter.from_poses(poses, full_cfg)
    step = []
    for _ in range(repeats // 3):
        t0 = time.perf_counter()
        pf.predict(np.array([0.05, 0.0, 0.01]), dt_s=0.1, rng=rng)
        pf.update(landmarks, bearings, rng=rng)
        pf.resample(rng=rng)
        step.append(time.perf_counter() - t0)
    return {
        "particles": n_particles,
        "landmarks": n_landmarks,
        "update_ms_median": 1e3 * float(np.median(update)),
        "update_ms_p90": 1e3 * float(np.percentile(update, 90)),
        "step_with_resampling_ms_median": 1e3 * float(np.median(step)),
        "update_from_spread_set_ms_median": 1e3 * float(np.median(staged)),
        "update_from_spread_set_stages_median": float(np.median(stages)),
    }


# --------------------------------------------------------------------------- 2. global
def _truth_at(gt: Trajectory, stamp: float) -> np.ndarray | None:
    ok, t = interpolate(gt, [stamp], max_gap_s=1.0)
    if not ok[0]:
        return None
    return np.array([t.xy[0, 0], t.xy[0, 1], t.theta[0]])


def _ate_of_results(rows: list[dict], gt: Any) -> float | None:
    """Position RMSE (m) of frame results' poses against ground truth at their stamps."""
    errs = []
    for r in rows:
        truth = _truth_at(gt, r["stamp"])
        if truth is not None:
            errs.append(np.hypot(r["pose"]["x"] - truth[0], r["pose"]["y"] - truth[1]))
    return float(np.sqrt(np.mean(np.square(errs)))) if errs else None


def _errors(est: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    return float(np.hypot(*(est[:2] - truth[:2]))), abs(wrap_angle(float(est[2] - truth[2])))


def _within(err: tuple[float, float]) -> bool:
    """Success tolerance of global localisation: 0.5 m and 15 degrees."""
    return err[0] <= 0.5 and err[1] <= math.radians(15)


def _median(values: list[Any]) -> float | None:
    kept = [v for v in values if v is not None]
    return float(np.median(kept)) if kept else None


def learn_places(
    loc: Localiser, frames: list[FrameInput], gt: Trajectory, landmarks: dict, span_s: float
) -> None:
    """Places along one robot's run at ground-truth poses (the map-building pass)."""
    t_end = frames[0].stamp + span_s
    for f in frames:
        if f.stamp > t_end:
            break
        truth = _truth_at(gt, f.stamp)
        if truth is None:
            continue
        track = loc.robots.get("mapper")
        if track is not None:
            track.seen.append(frozenset(o.label for o in f.observations))
            while len(track.seen) > loc.config.reliability_frames:
                track.seen.popleft()
        else:
            pf = ParticleFilter.from_poses(truth[None, :], loc.config.filter)
            loc.robots["mapper"] = RobotTrack(pf, TRACKING)
        if loc.places.should_learn(truth[:2], 1.0):
            loc.learn("mapper", truth, landmarks, frame=f.seq, stamp=f.stamp)
    loc.robots.pop("mapper", None)
    loc.places.last_visited.clear()


def _surveyed_runs(
    directory: Path,
) -> tuple[dict[str, np.ndarray], dict[int, tuple[list[FrameInput], Trajectory]]]:
    """The surveyed landmark map (label -> position) and robots 1-5's frames and truth."""
    data = {r: load_mrclam(directory, r) for r in range(1, 6)}
    lm_table = data[1].landmarks
    assert lm_table is not None
    landmarks = {str(int(s)): np.array([x, y]) for s, x, y in lm_table}
    return landmarks, {r: mrclam_frames(data[r]) for r in data}


def global_localisation(
    directory: Path,
    starts: int,
    max_frames: int,
    seed: int,
    config: LocaliserConfig | None = None,
) -> dict[str, Any]:
    landmarks, runs = _surveyed_runs(directory)
    base = Localiser(LocaliserConfig(learn_places=False))
    learn_places(base, runs[1][0], runs[1][1], landmarks, span_s=300.0)
    places_blob = base.places
    rows: list[dict[str, Any]] = []
    lengths = {r: len(v[0]) for r, v in runs.items()}
    for i, (robot, k0) in enumerate(_start_frames(lengths, starts, max_frames, seed)):
        frames, gt = runs[robot]
        cfg = config or LocaliserConfig()
        loc = Localiser(dataclasses.replace(cfg, learn_places=False), places=places_blob)
        loc.places.last_visited.clear()
        prng = np.random.default_rng([seed, i])
        converged_at = None
        err = (math.inf, math.inf)
        within: list[bool] = []  # the estimate within tolerance, per frame
        labels_seen: set[str] = set()
        t0 = time.perf_counter()
        for k in range(max_frames):
            f = frames[k0 + k]
            odo = None if k == 0 or f.odometry is None else (
                f.odometry.dx, f.odometry.dy, f.odometry.dtheta
            )  # fmt: skip
            res = loc.step(
                "r",
                odometry=odo,
                dt_s=0.0 if k == 0 else f.stamp - frames[k0 + k - 1].stamp,
                labels=[o.label for o in f.observations],
                bearings_rad=[o.bearing_rad for o in f.observations],
                sigmas_rad=[o.sigma_rad for o in f.observations],
                landmarks=landmarks,
                graph_pose=None,
                rng=prng,
            )
            labels_seen.update(o.label for o in f.observations)
            truth = _truth_at(gt, f.stamp)
            e = _errors(res.estimate.pose_xytheta, truth) if truth is not None else None
            within.append(e is not None and _within(e))
            if res.status == RELOCALISED:
                if e is not None:
                    err = e
                converged_at = k
                break
        ok = converged_at is not None and _within(err)
        # First frame from which the estimate stays within tolerance (up to relocalisation
        # or the last frame): the belief is right from there on, whether or not the
        # filter yet knows it (the convergence test's lag is frames_to_relocalise - this).
        good_from = next((k for k in range(len(within)) if all(within[k:])), None)
        rows.append(
            {
                "robot": robot,
                "start_frame": k0,
                "start_stamp": frames[k0].stamp,
                "frames_to_relocalise": converged_at,
                "observations_seen": sum(
                    len(frames[k0 + j].observations)
                    for j in range((converged_at or max_frames - 1) + 1)
                ),
                "frames_estimate_within_tolerance": good_from,
                "landmarks_seen": len(labels_seen),
                "error_m": err[0],
                "error_deg": math.degrees(err[1]),
                "success": ok,
                "ms": 1e3 * (time.perf_counter() - t0),
            }
        )
    frames_ok = [r["frames_to_relocalise"] for r in rows if r["success"]]
    return {
        "map": "surveyed landmark map (15 landmarks) + places learnt from robot 1, 0-300 s",
        "places": len(places_blob),
        "starts": starts,
        "max_frames": max_frames,
        "success_rate": float(np.mean([r["success"] for r in rows])),
        "median_frames_to_relocalise": float(np.median(frames_ok)) if frames_ok else None,
        "median_frames_estimate_within_tolerance": _median(
            [r["frames_estimate_within_tolerance"] for r in rows if r["success"]]
        ),
        "median_error_m": float(np.median([r["error_m"] for r in rows if r["success"]]))
        if frames_ok
        else None,
        "runs": rows,
    }


STUDY_VARIANTS: dict[str, tuple[str, dict[str, Any]]] = {
    "particles_20000": (
        "20000 particles throughout (no KLD): a belief not limited by sampling",
        {"min_particles": 20000, "max_particles": 20000},
    ),
    "converged_sigma_0.35m": (
        "the convergence test's largest position sigma 0.35 m instead of 0.25 m",
        {"converged_sigma_m": 0.35},
    ),
    "motion_from_odometry_statistics": (
        "motion noise from MRCLAM-6's odometry against ground truth per frame interval "
        "(straight: 0.3-0.7 cm and 0.6-1.0 deg rms; turning: up to 3.7 deg): smaller "
        "floors, 1.2 deg/sqrt(s), 0.2 rad/rad",
        {
            "motion_sigma_floor": (0.002, 0.002, math.radians(0.2)),
            "motion_sigma_per_sqrt_second": (0.006, 0.006, math.radians(1.2)),
            "motion_sigma_per_radian": 0.2,
        },
    ),
}
"""Filter settings the global-localisation study tries (why the median is what it is)."""


def global_study(directory: Path, starts: int, max_frames: int, seeds: list[int]) -> dict[str, Any]:
    """Global localisation again with each of STUDY_VARIANTS' filter settings."""
    out: dict[str, Any] = {}
    for name, (what, overrides) in STUDY_VARIANTS.items():
        config = LocaliserConfig(filter=FilterConfig(**overrides))
        rows = []
        for seed in seeds:
            doc = global_localisation(directory, starts, max_frames, seed, config)
            rows.append({"seed": seed, **{k: v for k, v in doc.items() if k in _SUMMARY}})
        out[name] = {"what": what, "runs": rows}
    return out


def global_check_study(directory: Path, starts: int, max_frames: int, seeds: list[int]) -> dict:
    """Global localisation on the surveyed map with and without the window check
    (graph.window_check): per seed, success, wrong convergences (`relocalised` beyond the
    tolerance), starts never relocalised, median frames."""
    out: dict[str, Any] = {}
    for name, window in (("without_check", 0), ("with_check", LocaliserConfig().verify_window)):
        rows = []
        for seed in seeds:
            doc = global_localisation(
                directory, starts, max_frames, seed, LocaliserConfig(verify_window=window)
            )
            runs = doc["runs"]
            rows.append(
                {
                    "seed": seed,
                    "success_rate": doc["success_rate"],
                    "wrong_relocalised": sum(
                        r["frames_to_relocalise"] is not None and not r["success"] for r in runs
                    ),
                    "never_relocalised": sum(r["frames_to_relocalise"] is None for r in runs),
                    "median_frames_to_relocalise": doc["median_frames_to_relocalise"],
                }
            )
            print(name, rows[-1], flush=True)
        out[name] = {"verify_window": window, "runs": rows}
    return out


_SUMMARY = (
    "success_rate",
    "median_frames_to_relocalise",
    "median_frames_estimate_within_tolerance",
    "median_error_m",
)


# ------------------------------------------------------------------ 2b. information bound
BOUND_THRESHOLDS_M = (0.2, 0.25, 0.35, 0.5)


def _start_frames(
    frames_per_robot: dict[int, int], starts: int, max_frames: int, seed: int
) -> Iterator[tuple[int, int]]:
    """(robot, start frame) of global localisation's starts for `seed` (the same draws)."""
    rng = np.random.default_rng(seed)
    for i in range(starts):
        robot = 1 + i % 5
        yield robot, int(rng.integers(0, frames_per_robot[robot] - max_frames - 1))


def frames_to_information(
    frames: list[FrameInput],
    gt: Trajectory,
    k0: int,
    max_frames: int,
    landmarks: dict[str, np.ndarray],
    filter_config: FilterConfig,
    bearing_sigma_rad: float | None,
) -> dict[float, int | None]:
    """First frame (from `k0`) at which even an estimator that knows the answer could be
    as sure as the convergence test asks: the Cramer-Rao bound of the latest pose given
    every frame's odometry (the filter's own motion noise) and labelled bearings to the
    surveyed landmarks, linearised at ground truth. Per position threshold t of
    BOUND_THRESHOLDS_M: the frame where the position's major-axis sigma is <= t and the
    heading's sigma <= converged_sigma_rad * t / converged_sigma_m (t = 0.25 m is the
    filter's test). The start has a prior of 10 m and pi rad (no initial pose).
    `bearing_sigma_rad` None: each observation's stated sigma."""
    xk, lk = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.L
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    lm_key = {}
    for j, (label, xy) in enumerate(landmarks.items()):
        lm_key[label] = lk(j)
        graph.add(gtsam.PriorFactorPoint2(lk(j), xy, gtsam.noiseModel.Isotropic.Sigma(2, 1e-4)))
        values.insert(lk(j), np.asarray(xy, dtype=np.float64))
    heading_per_m = filter_config.converged_sigma_rad / filter_config.converged_sigma_m
    found: dict[float, int | None] = dict.fromkeys(BOUND_THRESHOLDS_M)
    for k in range(max_frames):
        f = frames[k0 + k]
        truth = _truth_at(gt, f.stamp)
        if truth is None:
            break
        values.insert(xk(k), gtsam.Pose2(*truth))
        if k == 0:
            start = gtsam.noiseModel.Diagonal.Sigmas(np.array([10.0, 10.0, math.pi]))
            graph.add(gtsam.PriorFactorPose2(xk(0), gtsam.Pose2(*truth), start))
        elif f.odometry is None:
            raise ValueError(f"frame {f.seq} after the start carries no odometry")
        else:
            odo = np.array([f.odometry.dx, f.odometry.dy, f.odometry.dtheta])
            sig = motion_sigmas(odo, f.stamp - frames[k0 + k - 1].stamp, filter_config)
            graph.add(
                gtsam.BetweenFactorPose2(
                    xk(k - 1), xk(k), gtsam.Pose2(*odo), gtsam.noiseModel.Diagonal.Sigmas(sig)
                )
            )
        for o in f.observations:
            if o.label in lm_key:
                s = o.sigma_rad if bearing_sigma_rad is None else bearing_sigma_rad
                graph.add(
                    gtsam.BearingFactor2D(
                        xk(k), lm_key[o.label], gtsam.Rot2(o.bearing_rad),
                        gtsam.noiseModel.Isotropic.Sigma(1, s or filter_config.bearing_sigma_rad),
                    )
                )  # fmt: skip
        cov = gtsam.Marginals(graph, values).marginalCovariance(xk(k))
        pos = _major_sigma(cov[:2, :2])
        head = math.sqrt(float(cov[2, 2]))
        for t in BOUND_THRESHOLDS_M:
            if found[t] is None and pos <= t and head <= heading_per_m * t:
                found[t] = k
        if all(v is not None for v in found.values()):
            break
    return found


def information_bound(
    directory: Path, starts: int, max_frames: int, seeds: list[int], doc: dict[str, Any]
) -> dict[str, Any]:
    """frames_to_information over global localisation's starts (the same draws per seed),
    with the observations' stated sigma and with 0.5 deg (MRCLAM-6's bearing residual at
    ground truth is 0.3-0.6 deg); set beside the filter's frames to relocalise."""
    landmarks, runs = _surveyed_runs(directory)
    cfg = FilterConfig()
    models = {"stated": None, "0.5deg": math.radians(0.5)}
    rows = []
    for seed in seeds:
        lengths = {r: len(v[0]) for r, v in runs.items()}
        for i, (robot, k0) in enumerate(_start_frames(lengths, starts, max_frames, seed)):
            frames, gt = runs[robot]
            row: dict[str, Any] = {"seed": seed, "start": i, "robot": robot, "start_frame": k0}
            for name, sigma in models.items():
                got = frames_to_information(frames, gt, k0, max_frames, landmarks, cfg, sigma)
                row[name] = {str(t): v for t, v in got.items()}
            rows.append(row)
    summary: dict[str, Any] = {}
    for name in models:
        summary[name] = {}
        for t in BOUND_THRESHOLDS_M:
            ks = [r[name][str(t)] for r in rows if r[name][str(t)] is not None]
            summary[name][str(t)] = {
                "reached": len(ks),
                "median_frames": _median(ks),
                "per_seed_median_frames": [
                    _median([r[name][str(t)] for r in rows if r["seed"] == s]) for s in seeds
                ],
            }
    out: dict[str, Any] = {
        "what": "first frame at which the Cramer-Rao bound of the latest pose (odometry with "
        "the filter's motion noise + labelled bearings to the surveyed map, linearised at "
        "ground truth, start prior 10 m / pi) is within a position sigma t (major axis) and "
        "a heading sigma of 8 deg * t / 0.25 m; t = 0.25 m is the filter's convergence test",
        "seeds": seeds,
        "starts_per_seed": starts,
        "max_frames": max_frames,
        "summary": summary,
        "runs": rows,
    }
    pf = {(r["robot"], r["start_frame"]): r for r in doc.get("global", {}).get("runs", [])}
    paired = [
        (pf[(r["robot"], r["start_frame"])]["frames_to_relocalise"], r["stated"]["0.25"])
        for r in rows
        if (r["robot"], r["start_frame"]) in pf
        and pf[(r["robot"], r["start_frame"])]["success"]
        and r["stated"]["0.25"] is not None
    ]
    if paired:
        lag = [a - b for a, b in paired]
        out["filter_vs_bound_seed0"] = {
            "pairs": len(paired),
            "median_frames_filter_minus_bound": _median(lag),
            "filter_sooner_than_bound": int(sum(d < 0 for d in lag)),
        }
    return out


# ------------------------------------------------------------ 2c. on a map built online
HOLD_FRAMES = 20
"""A start succeeds when the reported pose stays within tolerance this many frames."""


def rest_config() -> dict[str, Any]:
    """The config a REST client's map gets when it gives none (the service's defaults:
    landmark cap, odometry random walks)."""
    return MapConfig().for_new_map(DEFAULT_LANDMARK_CAP).model_dump(mode="json")


def _map_frame(truth: Trajectory, rot: np.ndarray, trans: np.ndarray) -> Trajectory:
    """Ground truth moved into a map's frame, where `rot`, `trans` move the map's
    landmarks onto the surveyed ones (x_survey = rot @ x_map + trans)."""
    xy = (truth.xy - trans) @ rot  # rot.T @ (x - trans), row-wise
    turn = math.atan2(float(rot[1, 0]), float(rot[0, 0]))
    return Trajectory(truth.stamps, xy, truth.theta - turn)


def _copy_store(src: Path, dst: Path) -> None:
    for f in src.parent.glob(src.name + "*"):
        shutil.copyfile(f, dst.parent / (dst.name + f.name[len(src.name) :]))


MAP_SOURCES = ("session", "batch", "surveyed")
"""Where the online protocol's map comes from (``--online-map``): `session`, the map the
mapper built through the service; `batch`, the same map with its landmarks at a batch
Levenberg-Marquardt solution of the mapper's whole run (bench.batch) and that solution's
joint landmark marginal; `surveyed`, the surveyed landmarks with that same marginal."""


def build_online_map(
    directory: Path,
    mapper: int,
    where: Path,
    config: dict[str, Any],
    source: str = "session",
    transform: Callable[[MrclamRobot], MrclamRobot] | None = None,
) -> dict[str, Any]:
    """The map one robot builds through the service from its true initial pose (its
    whole run), stored at `where` with a snapshot; its landmarks fitted to the survey.
    `source` other than "session" replaces the map's estimate before it is stored (see
    MAP_SOURCES and `_replaced_map`); `transform` changes the robot's tables first (e.g.
    its odometry rescaled, bench.mrclam_sensors)."""
    data = load_mrclam(directory, mapper)
    if transform is not None:
        data = transform(data)
    assert data.landmarks is not None
    surveyed = {str(int(s)): np.array([x, y]) for s, x, y in data.landmarks}
    frames, gt = mrclam_frames(data)
    record = MapRecord("m", "online", "mapping", config, time.time())
    settings = StoreSettings(snapshot_every=100_000)
    session = MapSession.create(where, record, settings)
    t0 = time.perf_counter()
    for f in frames:
        session.submit(frame_to_dict(f))
    seconds = time.perf_counter() - t0
    replaced: dict[str, Any] = {}
    if source != "session":
        replaced = _replaced_map(session, frames, source, surveyed, gt)
    else:
        session.snapshot()
    session.close()
    session = MapSession(where, settings)  # the map as the starts will load it
    landmarks = landmark_map(session.slam)
    sigma = {k: _major_sigma(c) for k, c in landmark_covariances(session.slam).items()}
    shape = _shape_sigmas(session.slam)
    residuals = _bearing_residuals(session, frames, landmarks)
    assert session.pipeline.localiser is not None
    places = len(session.pipeline.localiser.localiser.places.places)
    session.close()
    if source != "session":  # the stored map holds what was put there
        centre = surveyed if source == "surveyed" else replaced["batch_map_landmarks"]
        off = {k: float(np.hypot(*(v - np.asarray(centre[k])))) for k, v in landmarks.items()}
        wide = replaced["batch_landmark_sigma_m"]
        # Within what LM left of the gradient (the marginal's linear term: a Gauss-Newton
        # step from where LM stopped).
        if max(off.values()) > 0.02 or any(abs(sigma[k] / wide[k] - 1) > 1e-3 for k in wide):
            raise RuntimeError(f"the replaced map moved: {off}, sigmas {sigma} against {wide}")
        replaced["landmarks_off_centre_max_m"] = max(off.values())
    fitted = _fitted(landmarks, surveyed)
    return {
        "source": source,
        "mapper": mapper,
        "frames": len(frames),
        "seconds": seconds,
        "landmarks": len(landmarks),
        "places": places,
        **fitted,
        "map_landmarks": {k: [float(v[0]), float(v[1])] for k, v in landmarks.items()},
        "landmark_sigma_m": sigma,
        "landmark_shape_sigma_m": shape,
        "mapper_bearing_residual_rms_deg": residuals,
        **replaced,
    }


def _shape_sigmas(slam: BearingSlam) -> dict[str, float]:
    """label -> major-axis sigma (m) of each live landmark in the map's joint landmark
    marginal with the rigid motion of the whole map taken out (a least-squares fit of
    a translation and a rotation about the landmarks' centroid): how sure the map is of
    where a landmark lies relative to the others, which is what a fit to the survey
    judges."""
    ids = sorted(slam.landmarks)
    xy = slam.landmark_positions(ids)
    joint = slam.landmark_joint_covariance(ids)
    d = xy - xy.mean(axis=0)
    rigid = np.zeros((2 * len(ids), 3))
    rigid[0::2, 0] = rigid[1::2, 1] = 1.0
    rigid[0::2, 2], rigid[1::2, 2] = -d[:, 1], d[:, 0]
    project = np.eye(2 * len(ids)) - rigid @ np.linalg.solve(rigid.T @ rigid, rigid.T)
    shape = project @ joint @ project.T
    return {
        slam.landmarks[i].label: _major_sigma(shape[2 * k : 2 * k + 2, 2 * k : 2 * k + 2])
        for k, i in enumerate(ids)
    }


def _bearing_residuals(
    session: MapSession, frames: list[FrameInput], landmarks: dict[str, np.ndarray]
) -> dict[str, float]:
    """label -> RMS (deg) of the mapping robot's bearings to the landmark against the
    map's final estimate (its trajectory and the landmark): how well the map fits the
    data it was built from, landmark by landmark."""
    robot = frames[0].robot
    stored = _stored_trajectory(session, robot, len(frames))
    if stored is None:
        return {}
    out: dict[str, list[float]] = {}
    for f, pose in zip(frames, stored.poses(), strict=True):
        seen = [o for o in f.observations if o.label in landmarks]
        if seen:
            predicted = predicted_bearings(pose[None], np.array([landmarks[o.label] for o in seen]))
            residual = wrap_angles(np.array([o.bearing_rad for o in seen]) - predicted[0])
            for o, r in zip(seen, residual.tolist(), strict=True):
                out.setdefault(o.label, []).append(r)
    return {k: math.degrees(float(np.sqrt(np.mean(np.square(v))))) for k, v in out.items()}


def _major_sigma(covariance: np.ndarray) -> float:
    """One-sigma along the major axis of a (2, 2) position covariance, metres."""
    return float(np.sqrt(np.linalg.eigvalsh(covariance)[-1]))


def _fitted(landmarks: dict[str, np.ndarray], surveyed: dict[str, np.ndarray]) -> dict[str, Any]:
    """The rigid fit of a map's landmarks to the surveyed ones: its figures, each
    landmark's distance from its surveyed position after the fit (in the map's frame),
    and the motion (`_rot`, `_trans`: x_survey = rot @ x_map + trans)."""
    fit = fit_landmarks(landmarks, surveyed)
    rot, trans = fit.motion
    return {
        "landmarks_fitted": len(fit.labels),
        "frame_rotation_deg": math.degrees(fit.rotation_rad),
        "frame_shift_m": fit.shift_m,
        "landmark_rmse_m": fit.rmse_m,
        "landmark_rmse_in_map_frame_m": fit.rmse_aligned_m,
        "landmark_error_in_map_frame_m": fit.errors_by_label(),
        "landmark_similarity_scale": fit.scale,
        "_rot": rot,
        "_trans": trans,
    }


def _stored_trajectory(session: MapSession, robot: str, frames: int) -> Trajectory | None:
    """A robot's whole trajectory in a session's map (the store's final rows and the
    graph's held ones); None unless it has one row per frame."""
    rows: dict[int, np.ndarray] = {}
    for source in (session.store.poses(robot), session.slam.trajectory(robot)):
        rows.update({int(r[0]): r for r in source.get(robot, np.zeros((0, 5)))})
    if len(rows) != frames:
        return None
    table = np.array([rows[k] for k in sorted(rows)])
    return Trajectory.from_poses(table[:, 1], table[:, 2:5])


def _replaced_map(
    session: MapSession,
    frames: list[FrameInput],
    source: str,
    surveyed: dict[str, np.ndarray],
    gt: Trajectory,
) -> dict[str, Any]:
    """Store a snapshot of `session` whose estimate is replaced (the map's records, places
    and the mapper's pose window stay): a batch Levenberg-Marquardt solution of the
    mapper's whole run (bench.batch, from dead reckoning and from the session's own
    trajectory) is marginalised onto the map's landmarks, and that joint marginal becomes
    the graph's only landmark factor, centred at the batch's landmarks (`batch`) or at the
    surveyed ones (`surveyed`). The mapper's live poses keep their batch marginal each as
    a prior, at the batch pose or the true one, unlinked from the landmarks (the mapper
    sends no more frames). Returns what was replaced: the session's landmarks and the
    batch's figures."""
    slam = session.slam
    robot = frames[0].robot
    before = landmark_map(slam)
    ids = landmark_ids(slam)
    solved = batch_solve(
        frames, slam.config, online=_stored_trajectory(session, robot, len(frames))
    ).per_start
    # Costs compare only between solutions of the same landmarks: a start that could not
    # triangulate a landmark leaves its bearings out (dead reckoning misses landmark 18).
    most = max(len(r.landmark_xy) for r in solved.values())
    batch = min((r for r in solved.values() if len(r.landmark_xy) == most), key=lambda r: r.cost)
    missing = sorted(set(ids) - set(batch.landmark_xy))
    if missing:
        raise RuntimeError(f"the batch solution has no landmarks {missing}")
    labels = dict(ids)
    for label in batch.landmark_xy:  # the batch's landmarks the map does not hold
        labels.setdefault(label, max(labels.values()) + 1)
    graph = batch_graph(frames, slam.config, {k: labels[k] for k in batch.landmark_xy})
    values = gtsam.Values()
    for k, (x, y, theta) in enumerate(batch.trajectory.poses()):
        values.insert(pose_key(0, k), gtsam.Pose2(float(x), float(y), float(theta)))
    for label, xy in batch.landmark_xy.items():
        values.insert(landmark_key(labels[label]), np.array(xy, dtype=np.float64))
    kept = {landmark_key(i) for i in ids.values()}
    others = [k for k in values.keys() if k not in kept]
    _, remaining = graph.linearize(values).eliminatePartialMultifrontal(gtsam.Ordering(others))
    at = gtsam.Values()  # where the replaced estimate is centred
    for label, i in ids.items():
        centre = surveyed[label] if source == "surveyed" else np.array(batch.landmark_xy[label])
        at.insert(landmark_key(i), np.asarray(centre, dtype=np.float64))
    factors = gtsam.NonlinearFactorGraph()
    for i in range(remaining.size()):
        factor = remaining.at(i)
        if factor is not None and len(factor.keys()) > 0:
            point = gtsam.Values()
            for key in factor.keys():
                point.insert(key, at.atPoint2(key))
            factors.add(gtsam.LinearContainerFactor(factor, point))
    containers = factors.size()
    marginals = gtsam.Marginals(graph, values)
    for key in slam.graph.linearization_point().keys():
        if is_landmark_key(key):
            continue
        k = gtsam.Symbol(key).index()  # the mapper's slot is 0, its pose index the frame's
        pose = values.atPose2(key)
        truth = _truth_at(gt, frames[k].stamp) if source == "surveyed" else None
        if truth is not None:
            pose = gtsam.Pose2(*map(float, truth))
        at.insert(key, pose)
        noise = gtsam.noiseModel.Gaussian.Covariance(marginals.marginalCovariance(key))
        factors.add(gtsam.PriorFactorPose2(key, pose, noise))
    blob, _ = snapshot_pipeline(session.pipeline)
    state = pickle.loads(blob)
    state["factors"] = factors.serialize()
    state["relative"] = []
    state["linpoint"] = at.serialize()
    state["graph"].update(
        _marginals=set(range(containers)),
        marginal_keys=[],
        _pose_cache={},
        _point_cache={},
        _cov_cache={},
    )
    session.store.save_snapshot(session.last_log_id, pickle.dumps(state), keep=1)
    # The session's landmarks against the batch's, after the rigid fit of one to the other.
    rot, trans = align_se2(
        np.array([before[k] for k in ids]),
        np.array([batch.landmark_xy[k] for k in ids], dtype=np.float64),
    )
    return {
        "session_landmarks": {k: [float(v[0]), float(v[1])] for k, v in before.items()},
        "session_landmark_rmse_in_map_frame_m": _fitted(before, surveyed)[
            "landmark_rmse_in_map_frame_m"
        ],
        "batch_start": batch.start,
        "batch_cost": batch.cost,
        "batch_starts": {
            name: {"cost": r.cost, "landmarks": len(r.landmark_xy)} for name, r in solved.items()
        },
        "batch_landmarks": len(batch.landmark_xy),
        "batch_map_landmarks": {k: [float(v) for v in batch.landmark_xy[k]] for k in ids},
        "batch_landmark_sigma_m": {
            k: _major_sigma(marginals.marginalCovariance(landmark_key(labels[k]))) for k in ids
        },
        "session_minus_batch_m": {
            k: float(np.hypot(*(rot @ before[k] + trans - np.asarray(batch.landmark_xy[k]))))
            for k in ids
        },
    }


def _online_start(
    where: Path,
    tmp: Path,
    name: str,
    frames: list[FrameInput],
    gt: Trajectory,
    k0: int,
    max_frames: int,
    window: WindowCheckConfig | None = None,
) -> dict[str, Any]:
    """One robot entering the stored map at frame `k0` without an initial pose: frames
    through a copy of the map until success is settled or `max_frames` + HOLD_FRAMES.
    `window`: the localiser's check of a converged filter, in place of the map's own."""
    path = tmp / f"{name}.sqlite"
    _copy_store(where, path)
    session = MapSession(path, StoreSettings(snapshot_every=100_000))
    if window is not None:
        assert session.pipeline.localiser is not None
        localiser = session.pipeline.localiser.localiser
        localiser.config = dataclasses.replace(localiser.config, window_check=window)
    stream = frames[k0 : k0 + max_frames + HOLD_FRAMES]
    stream = [dataclasses.replace(stream[0], initial_pose=None), *stream[1:]]
    events: list[dict[str, Any]] = []
    within: list[bool] = []
    success_at = None
    t0 = time.perf_counter()
    for k, f in enumerate(stream):
        r = json.loads(session.submit(frame_to_dict(f)).result_json)
        truth = _truth_at(gt, f.stamp)
        pose = r.get("pose")
        err = None
        if truth is not None and pose is not None:
            err = _errors(np.array([pose["x"], pose["y"], pose["theta"]]), truth)
        within.append(err is not None and _within(err))
        if r["localisation"]["status"] == RELOCALISED:
            events.append(
                {
                    "frame": k,
                    "error_m": None if err is None else err[0],
                    "error_deg": None if err is None else math.degrees(err[1]),
                    "within": within[-1],
                    "pose": None if pose is None else [pose["x"], pose["y"], pose["theta"]],
                }
            )
        for e in events:
            held = k == e["frame"] + HOLD_FRAMES - 1 and all(within[e["frame"] :])
            if success_at is None and e["frame"] <= max_frames and held:
                success_at = e["frame"]
        if success_at is not None:
            break
    session.close()
    for copy in tmp.glob(f"{name}.sqlite*"):
        copy.unlink()
    return {
        "frames_run": len(within),
        "relocalised": events,
        "frames_to_success": success_at,
        "success": success_at is not None,
        "wrong_relocalised": sum(not e["within"] for e in events),
        "labels_seen": sorted({o.label for f in stream[: len(within)] for o in f.observations}),
        "ms": 1e3 * (time.perf_counter() - t0),
    }


def frames_to_information_ekf(
    frames: list[FrameInput],
    gt: Trajectory,
    k0: int,
    max_frames: int,
    landmarks: dict[str, np.ndarray],
    filter_config: FilterConfig,
) -> int | None:
    """`frames_to_information` at the filter's test (0.25 m), computed another way: the
    covariance of an extended Kalman filter linearised at the truth (numpy, no GTSAM),
    from the same prior, motion noise and bearings. A cross-check of the bound's code."""
    cov = np.diag([100.0, 100.0, math.pi**2])
    prev = None
    for k in range(max_frames):
        f = frames[k0 + k]
        truth = _truth_at(gt, f.stamp)
        if truth is None:
            return None
        if prev is not None and f.odometry is not None:
            odo = np.array([f.odometry.dx, f.odometry.dy, f.odometry.dtheta])
            sig = motion_sigmas(odo, f.stamp - frames[k0 + k - 1].stamp, filter_config)
            c, s = math.cos(prev[2]), math.sin(prev[2])
            jac = np.array([[1, 0, -s * odo[0] - c * odo[1]], [0, 1, c * odo[0] - s * odo[1]],
                            [0, 0, 1]])  # fmt: skip
            turn = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
            cov = jac @ cov @ jac.T + turn @ np.diag(np.square(sig)) @ turn.T
        for o in f.observations:
            if o.label in landmarks:
                d = landmarks[o.label] - truth[:2]
                h = np.array([d[1], -d[0], -(d @ d)]) / (d @ d)
                s2 = (o.sigma_rad or filter_config.bearing_sigma_rad) ** 2
                ch = cov @ h
                cov = cov - np.outer(ch, ch) / (h @ ch + s2)
        prev = truth
        if (
            _major_sigma(cov[:2, :2]) <= filter_config.converged_sigma_m
            and math.sqrt(cov[2, 2]) <= filter_config.converged_sigma_rad
        ):
            return k
    return None


def map_implied_pose(
    frames: list[FrameInput],
    landmarks: dict[str, np.ndarray],
    truth_xytheta: np.ndarray,
    filter_config: FilterConfig,
) -> np.ndarray:
    """(3,) the latest pose of `frames` that the map's `landmarks` imply: the frames'
    odometry and labelled bearings solved against the map (landmarks held, the window
    check's small pose graph) from the true latest pose. A localiser that reports this
    pose is right about the map; its distance from the truth is the map's error there."""
    pf = ParticleFilter.from_poses(np.zeros((1, 3)), filter_config)
    window = []
    for k, f in enumerate(frames):
        seen = [o for o in f.observations if o.label in landmarks]
        odo = None
        if k > 0 and f.odometry is not None:
            odo = np.array([f.odometry.dx, f.odometry.dy, f.odometry.dtheta])
        sig = np.array([np.nan if o.sigma_rad is None else o.sigma_rad for o in seen])
        window.append(
            WindowFrame(
                odo,
                0.0 if k == 0 else f.stamp - frames[k - 1].stamp,
                np.array([landmarks[o.label] for o in seen], dtype=np.float64).reshape(-1, 2),
                np.array([o.bearing_rad for o in seen], dtype=np.float64),
                pf.bearing_sigmas(len(seen), sig),
            )
        )
    got = check_window(truth_xytheta, np.diag([0.01, 0.01, 1e-4]), window, filter_config)
    return np.asarray(got.pose_xytheta, dtype=np.float64)


def map_admitted_success(
    frames: list[FrameInput],
    gt_map: Trajectory,
    k0: int,
    from_frame: int | None,
    max_frames: int,
    landmarks: dict[str, np.ndarray],
    filter_config: FilterConfig,
) -> int | None:
    """The first frame k in [`from_frame`, `max_frames`] (counted from the start at `k0`)
    from which the pose the map implies (map_implied_pose over the frames since the start)
    lies within the success tolerance of the truth for HOLD_FRAMES frames in a row: the
    earliest a localiser that reports where the map puts the robot could succeed. None
    when no such run starts by `max_frames`, or when `from_frame` is None. Start it at the
    information bound's frame: before it the frames do not fix the pose, and a solve from
    the truth stays near the truth. Optimistic (each solve starts at the truth), so the
    share of starts it admits bounds any map-trusting localiser's success from above."""
    if from_frame is None:
        return None
    run = 0
    for k in range(from_frame, min(max_frames + HOLD_FRAMES, len(frames) - k0)):
        truth = _truth_at(gt_map, frames[k0 + k].stamp)
        ok = False
        if truth is not None:
            implied = map_implied_pose(frames[k0 : k0 + k + 1], landmarks, truth, filter_config)
            ok = _within(_errors(implied, truth))
        run = run + 1 if ok else 0
        if run == HOLD_FRAMES:
            return k - HOLD_FRAMES + 1
        if k - run >= max_frames:
            return None
    return None


def online_localisation(
    directory: Path,
    mapper: int,
    starts_per_robot: int,
    max_frames: int,
    seeds: list[int],
    bound: bool = True,
    source: str = "session",
    window: WindowCheckConfig | None = None,
) -> dict[str, Any]:
    """One robot maps through the service (a REST client's default config, its true
    initial pose); the other robots then enter the map without an initial pose, each
    from `starts_per_robot` random frames per seed. Judged in the map's own frame: ground
    truth moved by the fit of the map's landmarks to the surveyed ones. Beside each first
    `relocalised`, the pose the map itself implies there (see _against_the_map).
    `source`: the map's estimate replaced before the starts (MAP_SOURCES); `window`: the
    localiser's check of a converged filter (default: the map's own)."""
    config = rest_config()
    runs = {r: mrclam_frames(load_mrclam(directory, r)) for r in range(1, 6) if r != mapper}
    rows: list[dict[str, Any]] = []
    implied_cfg = map_localiser_config().filter
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        where = tmp / "map.sqlite"
        built = build_online_map(directory, mapper, where, config, source)
        rot, trans = built.pop("_rot"), built.pop("_trans")
        residual = built["landmark_error_in_map_frame_m"]
        map_xy = {k: np.array(v) for k, v in built["map_landmarks"].items()}
        bound_cfg = FilterConfig()
        for seed in seeds:
            rng = np.random.default_rng(seed)
            for robot, (frames, gt) in runs.items():
                gt_map = _map_frame(gt, rot, trans)
                for i in range(starts_per_robot):
                    k0 = int(rng.integers(0, len(frames) - max_frames - HOLD_FRAMES - 1))
                    row: dict[str, Any] = {"seed": seed, "robot": robot, "start_frame": k0}
                    row.update(
                        _online_start(where, tmp, f"s{seed}r{robot}i{i}", frames, gt_map, k0,
                                      max_frames, window)
                    )  # fmt: skip
                    _against_the_map(row, frames, gt_map, k0, map_xy, implied_cfg)
                    # How far off (in the map's frame) the landmarks this start saw sit:
                    # a pose consistent with them is that far off too.
                    seen = [residual[k] for k in row["labels_seen"] if k in residual]
                    row["seen_landmarks_error_rms_m"] = (
                        float(np.sqrt(np.mean(np.square(seen)))) if seen else None
                    )
                    if bound:
                        got = frames_to_information(
                            frames, gt_map, k0, max_frames, map_xy, bound_cfg, None
                        )
                        row["frames_to_information"] = got[0.25]
                        row["frames_to_information_ekf"] = frames_to_information_ekf(
                            frames, gt_map, k0, max_frames, map_xy, bound_cfg
                        )
                        row["map_admits_success_at"] = map_admitted_success(
                            frames, gt_map, k0, got[0.25], max_frames, map_xy, implied_cfg
                        )
                    rows.append(row)
                    print(
                        {k: v for k, v in row.items() if k not in ("relocalised", "labels_seen")},
                        [(e["frame"], round(e["error_m"] or -1, 2)) for e in row["relocalised"]],
                        flush=True,
                    )
    checked = {} if window is None else {"window_check": dataclasses.asdict(window)}
    return {
        "map": built,
        "config": config,
        **checked,
        **_online_summary(rows, max_frames),
        "runs": rows,
    }


def _against_the_map(
    row: dict[str, Any],
    frames: list[FrameInput],
    gt_map: Trajectory,
    k0: int,
    map_xy: dict[str, np.ndarray],
    filter_config: FilterConfig,
) -> None:
    """Beside a start's first `relocalised` frame: the pose the map implies there
    (map_implied_pose over the frames since the start), how far it lies from the truth
    (the map's own error) and from the reported pose (the localiser's error against its
    map)."""
    if not row["relocalised"]:
        return
    event = row["relocalised"][0]
    k = event["frame"]
    truth = _truth_at(gt_map, frames[k0 + k].stamp)
    if truth is None or event["pose"] is None:
        return
    implied = map_implied_pose(frames[k0 : k0 + k + 1], map_xy, truth, filter_config)
    event["map_implied_error_m"] = _errors(implied, truth)[0]
    off = _errors(np.asarray(event["pose"]), implied)
    event["error_to_map_implied_m"] = off[0]
    event["error_to_map_implied_deg"] = math.degrees(off[1])
    event["within_of_map_implied"] = _within(off)


def _online_summary(rows: list[dict[str, Any]], max_frames: int) -> dict[str, Any]:
    ok = [r for r in rows if r["success"]]
    admitted = [r for r in rows if r.get("map_admits_success_at") is not None]
    info = [r.get("frames_to_information") for r in rows]
    med_success, med_info = _median([r["frames_to_success"] for r in ok]), _median(info)
    paired = [
        r["frames_to_success"] / r["frames_to_information"]
        for r in ok
        if r.get("frames_to_information")
    ]
    return {
        "starts": len(rows),
        "max_frames": max_frames,
        "hold_frames": HOLD_FRAMES,
        "success_rate": len(ok) / len(rows) if rows else None,
        "median_frames_to_success": med_success,
        "median_frames_to_information": med_info,
        "information_reached": sum(v is not None for v in info),
        "information_reached_ekf": sum(
            r.get("frames_to_information_ekf") is not None for r in rows
        ),
        "median_ratio_success_to_information": _median(paired),
        "ratio_of_medians": None if med_success is None or not med_info else med_success / med_info,
        "wrong_convergence_rate": sum(r["wrong_relocalised"] > 0 for r in rows) / len(rows)
        if rows
        else None,
        "wrong_relocalised_events": sum(r["wrong_relocalised"] for r in rows),
        "relocalised_then_drifted": sum(
            1 for r in rows if not r["success"] and any(e["within"] for e in r["relocalised"])
        ),
        "never_relocalised": sum(1 for r in rows if not r["relocalised"]),
        # The map's own bound on success (map_admitted_success): the share of starts at
        # which the pose the map implies holds within the tolerance for HOLD_FRAMES frames
        # from the information bound on, and the localiser's successes among them.
        "map_admits_success_rate": len(admitted) / len(rows) if rows else None,
        "success_where_map_admits": (
            sum(r["success"] for r in admitted) / len(admitted) if admitted else None
        ),
        "wrong_where_map_does_not_admit": sum(
            r["wrong_relocalised"] > 0 for r in rows if r.get("map_admits_success_at") is None
        ),
        "wrong_convergences": [
            {
                "robot": r["robot"],
                "start_frame": r["start_frame"],
                "seed": r["seed"],
                **{k: v for k, v in e.items() if k not in ("within", "pose")},
                "seen_landmarks_error_rms_m": r.get("seen_landmarks_error_rms_m"),
            }
            for r in rows
            for e in r["relocalised"]
            if not e["within"]
        ],
        "wrong_against_the_map": [
            {
                "robot": r["robot"],
                "start_frame": r["start_frame"],
                "seed": r["seed"],
                **{k: v for k, v in r["relocalised"][0].items() if k != "pose"},
            }
            for r in rows
            if r["relocalised"] and not r["relocalised"][0].get("within_of_map_implied", True)
        ],
        "median_frames_to_relocalise": _median(
            [r["relocalised"][0]["frame"] for r in rows if r["relocalised"]]
        ),
        "per_robot": {
            str(robot): _per_robot([r for r in rows if r["robot"] == robot])
            for robot in sorted({r["robot"] for r in rows})
        },
        "per_robot_success": {
            str(robot): float(np.mean([r["success"] for r in rows if r["robot"] == robot]))
            for robot in sorted({r["robot"] for r in rows})
        },
    }


def _per_robot(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """One robot's starts: success, wrong convergences, median frames to success and the
    bound's median frames."""
    return {
        "starts": len(rows),
        "success_rate": float(np.mean([r["success"] for r in rows])),
        "wrong_convergence_rate": float(np.mean([r["wrong_relocalised"] > 0 for r in rows])),
        "median_frames_to_success": _median([r["frames_to_success"] for r in rows if r["success"]]),
        "median_frames_to_information": _median([r.get("frames_to_information") for r in rows]),
        "map_admits_success_rate": float(
            np.mean([r.get("map_admits_success_at") is not None for r in rows])
        ),
    }


def _cut_stream(
    frames: list[FrameInput], t0: float, before_s: float, cut_s: float, after_s: float
) -> tuple[list[FrameInput], int]:
    """A robot's frames with `cut_s` seconds cut out after `before_s`: the first frame
    after the gap carries zero odometry (the robot jumps). The stream and the cut's index."""
    pre = [f for f in frames if f.stamp < t0 + before_s]
    t1 = t0 + before_s + cut_s
    post = [f for f in frames if t1 <= f.stamp < t1 + after_s]
    jump = dataclasses.replace(post[0], odometry=Odometry(0.0, 0.0, 0.0))
    return [*pre, jump, *post[1:]], len(pre)


SWAP_MIN_JUMP_M = 1.5
"""A swap happens at the first frame after `before_s` at which the two robots are at
least this far apart (MRCLAM's robots often pass close to each other)."""


def _swap_time(
    mine: Trajectory, other: Trajectory, frames: list[FrameInput], after: float
) -> float:
    """Stamp of the first of `frames` after `after` at which the robots' true positions
    are at least SWAP_MIN_JUMP_M apart."""
    for f in frames:
        a, b = _truth_at(mine, f.stamp), _truth_at(other, f.stamp)
        apart = a is not None and b is not None and np.hypot(*(a[:2] - b[:2]))
        if f.stamp >= after and apart and apart >= SWAP_MIN_JUMP_M:
            return f.stamp
    raise ValueError("the robots are never that far apart")


def _swap_stream(
    frames: list[FrameInput], other: list[FrameInput], t1: float, after_s: float
) -> tuple[list[FrameInput], int]:
    """A robot's frames until `t1`, then another robot's frames under its name
    (renumbered): the robot is suddenly where the other one is, and nothing in the
    odometry says so (the first swapped frame carries the other robot's own motion)."""
    pre = [f for f in frames if f.stamp < t1]
    post = [f for f in other if t1 <= f.stamp < t1 + after_s]
    name = frames[0].robot
    stream = [*pre, *(dataclasses.replace(f, robot=name) for f in post)]
    return [dataclasses.replace(f, seq=i) for i, f in enumerate(stream)], len(pre)


def _spliced_truth(before: Trajectory, after: Trajectory, t_cut: float) -> Trajectory:
    """`before`'s samples before `t_cut` and `after`'s from it (the swapped robot's truth)."""
    a, b = before.stamps < t_cut, after.stamps >= t_cut
    return Trajectory(
        np.concatenate([before.stamps[a], after.stamps[b]]),
        np.vstack([before.xy[a], after.xy[b]]),
        np.concatenate([before.theta[a], after.theta[b]]),
    )


DATA_TELL_PRIOR = (0.15, 0.15, math.radians(3.0))
"""Sigmas (m, m, rad) of the old pose at a kidnap in `frames_until_data_tell`: about
what a tracked robot's pose is known to in the online map (ATE 0.13-0.38 m before the
cuts); the localiser's own test adds kidnap_sigma_floor to the graph's covariance."""


def frames_until_data_tell(
    stream: list[FrameInput],
    cut: int,
    truth: Trajectory,
    landmarks: dict[str, np.ndarray],
    config: LocaliserConfig,
    max_frames: int = 60,
) -> int | None:
    """First frame after the cut at which the frames since then reject the old pose as
    the localiser's test does (graph.window_check.rejects_old_pose at
    `config.kidnap_gate`), but with what no detector has: the old pose is the truth just
    before the cut (DATA_TELL_PRIOR), and the free solution starts at the truth. The
    frames are the service's (the jump's odometry as it receives it), the bearings to
    `landmarks` with the filter's sigmas. None: not within `max_frames` frames."""
    before = _truth_at(truth, stream[cut - 1].stamp)
    if before is None:
        return None
    pf = ParticleFilter.from_poses(before[None, :], config.filter)
    window: list[WindowFrame] = []
    for k in range(min(max_frames, len(stream) - cut)):
        f, prev = stream[cut + k], stream[cut + k - 1]
        odo = None if f.odometry is None else np.array(
            [f.odometry.dx, f.odometry.dy, f.odometry.dtheta]
        )  # fmt: skip
        seen = [o for o in f.observations if o.label in landmarks]
        lm = np.array([landmarks[o.label] for o in seen], dtype=np.float64).reshape(-1, 2)
        z = np.array([o.bearing_rad for o in seen], dtype=np.float64)
        sig = pf.bearing_sigmas(len(z), np.array([o.sigma_rad or np.nan for o in seen]))
        labels = tuple(o.label for o in seen)
        window.append(WindowFrame(odo, f.stamp - prev.stamp, lm, z, sig, labels))
        latest = _truth_at(truth, f.stamp)
        if not len(z) or latest is None:
            continue
        rejected, _ = rejects_old_pose(
            before,
            np.diag(np.square(DATA_TELL_PRIOR)),
            window,
            config.filter,
            config.kidnap_gate,
            latest_xytheta=[latest],
        )
        if rejected:
            return k
    return None


def online_kidnap(
    directory: Path,
    mapper: int,
    before_s: float,
    cut_s: float,
    after_s: float,
    *,
    swap: bool = False,
) -> dict[str, Any]:
    """Kidnapping in the map one robot built (as `online_localisation`): each other robot
    enters a copy of it at its true first pose (moved into the map's frame), tracks for
    `before_s`, then either loses `cut_s` of frames (a jump without odometry) or, with
    `swap`, goes on with the next robot's frames under its own name (robot 2 gets 3's,
    ..., 5 gets 2's) from the first frame the two are SWAP_MIN_JUMP_M apart; then runs
    `after_s`. Judged in the map's frame: frames from the jump to `lost` and to
    `relocalised`, the error then, whether the 20 frames after it hold the tolerance;
    false `lost` before; when the data could first tell (`frames_until_data_tell`)."""
    rows = []
    others = [r for r in range(1, 6) if r != mapper]
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        where = tmp / "map.sqlite"
        built = build_online_map(directory, mapper, where, rest_config())
        rot, trans = built.pop("_rot"), built.pop("_trans")
        map_xy = {k: np.array(v) for k, v in built["map_landmarks"].items()}
        runs = {r: mrclam_frames(load_mrclam(directory, r)) for r in others}
        for i, robot in enumerate(others):
            frames, gt = runs[robot]
            gt_map = _map_frame(gt, rot, trans)
            t0 = frames[0].stamp
            if swap:
                source = others[(i + 1) % len(others)]
                t1 = _swap_time(gt, runs[source][1], frames, t0 + before_s)
                stream, cut = _swap_stream(frames, runs[source][0], t1, after_s)
                split = 0.5 * (stream[cut - 1].stamp + stream[cut].stamp)
                truth = _spliced_truth(gt_map, _map_frame(runs[source][1], rot, trans), split)
            else:
                source = robot
                stream, cut = _cut_stream(frames, t0, before_s, cut_s, after_s)
                truth = gt_map
            start = _truth_at(gt_map, t0)
            assert start is not None
            stream[0] = dataclasses.replace(
                stream[0], initial_pose=Pose2D(*(float(v) for v in start))
            )
            path = tmp / f"k{robot}.sqlite"
            _copy_store(where, path)
            session = MapSession(path, StoreSettings(snapshot_every=100_000))
            results = [json.loads(session.submit(frame_to_dict(f)).result_json) for f in stream]
            session.close()
            errs = []
            for r in results:
                at = _truth_at(truth, r["stamp"])
                pose = r.get("pose")
                errs.append(
                    None
                    if at is None or pose is None
                    else _errors(np.array([pose["x"], pose["y"], pose["theta"]]), at)
                )
            after = _after_cut(results, cut, truth)
            reloc = after["frames_to_relocalised"]
            held = None
            if reloc is not None:
                window = errs[cut + reloc : cut + reloc + HOLD_FRAMES]
                held = len(window) == HOLD_FRAMES and all(
                    e is not None and _within(e) for e in window
                )
            at = None if reloc is None else errs[cut + reloc]
            tell = frames_until_data_tell(stream, cut, truth, map_xy, map_localiser_config())
            lost = after["frames_to_lost"]
            # How soon any estimator could know where the robot is after the jump (2b's
            # bound on the map's own landmarks, from the jump without a prior).
            bound = frames_to_information(stream, truth, cut, 150, map_xy, FilterConfig(), None)
            info = bound[0.25]
            rows.append(
                {
                    "robot": robot,
                    "frames_of": source,
                    "frames_before": cut,
                    "jump_m": _jump(truth, stream[cut - 1].stamp, stream[cut].stamp),
                    "frames_until_observed": next(
                        (k for k, f in enumerate(stream[cut:]) if f.observations), None
                    ),
                    "frames_until_data_tell": tell,
                    **after,
                    "lost_within_20_of_data_tell": None
                    if tell is None
                    else lost is not None and lost <= tell + 20,
                    "frames_to_information": info,
                    "relocalised_within_bound_plus_10": None
                    if info is None
                    else reloc is not None and reloc <= info + 10,
                    "error_at_relocalised_m": None if at is None else at[0],
                    "error_at_relocalised_deg": None if at is None else math.degrees(at[1]),
                    "held_20_frames": held,
                    # Whatever the status said: how far off the reported poses were from
                    # 20 frames after the jump on (a graph that recovers needs no `lost`).
                    "ate_from_20_frames_after_cut_m": _ate_of_results(
                        results[cut + HOLD_FRAMES :], truth
                    ),
                }
            )
            print(rows[-1], flush=True)
    return {
        "map": built,
        "kind": "swap" if swap else "cut",
        "before_s": before_s,
        "cut_s": 0.0 if swap else cut_s,
        "after_s": after_s,
        "data_tell_prior_sigmas": [DATA_TELL_PRIOR[0], DATA_TELL_PRIOR[1],
                                   math.degrees(DATA_TELL_PRIOR[2])],
        "runs": rows,
    }  # fmt: skip


def online_tracking(directory: Path, mapper: int) -> dict[str, Any]:
    """Each other robot's whole run, no kidnap, in the map one robot built (as
    `online_localisation`), from its true first pose: every `lost` is a false alarm."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        where = tmp / "map.sqlite"
        built = build_online_map(directory, mapper, where, rest_config())
        rot, trans = built.pop("_rot"), built.pop("_trans")
        for robot in (r for r in range(1, 6) if r != mapper):
            frames, gt = mrclam_frames(load_mrclam(directory, robot))
            gt_map = _map_frame(gt, rot, trans)
            start = _truth_at(gt_map, frames[0].stamp)
            assert start is not None
            first = dataclasses.replace(frames[0], initial_pose=Pose2D(*(float(v) for v in start)))
            path = tmp / f"t{robot}.sqlite"
            _copy_store(where, path)
            session = MapSession(path, StoreSettings(snapshot_every=100_000))
            results = [
                json.loads(session.submit(frame_to_dict(f)).result_json)
                for f in [first, *frames[1:]]
            ]
            session.close()
            statuses = [r["localisation"]["status"] for r in results]
            # The frame's time outside the graph's step (localiser, bookkeeping), which
            # the old-pose test adds to on the frames the graph's pose does not explain.
            localise = np.array([r["timing_ms"].get("localise", np.nan) for r in results])
            rows.append(
                {
                    "robot": robot,
                    "frames": len(frames),
                    "lost_events": _lost_events(statuses),
                    "lost_frames": statuses.count("lost"),
                    "ate_m": _ate_of_results(results, gt_map),
                    "localise_ms_median": float(np.nanmedian(localise)),
                    "localise_ms_p99": float(np.nanpercentile(localise, 99)),
                    "localise_ms_max": float(np.nanmax(localise)),
                }
            )
            print(rows[-1], flush=True)
    return {"map_landmarks": built["landmarks"], "runs": rows}


# --------------------------------------------------------------------------- 3. kidnap
def _jump(gt: Trajectory, t_from: float, t_to: float) -> float | None:
    a, b = _truth_at(gt, t_from), _truth_at(gt, t_to)
    return None if a is None or b is None else float(np.hypot(*(b[:2] - a[:2])))


def kidnap(
    directory: Path, robot: int, before_s: float, cut_s: float, after_s: float
) -> dict[str, Any]:
    frames, gt = mrclam_frames(load_mrclam(directory, robot))
    t0 = frames[0].stamp
    pre = [f for f in frames if f.stamp < t0 + before_s]
    post = [f for f in frames if t0 + before_s + cut_s <= f.stamp < t0 + before_s + cut_s + after_s]
    first = post[0]
    jump = dataclasses.replace(first, odometry=Odometry(0.0, 0.0, 0.0))  # no odometry for the gap
    stream = [*pre, jump, *post[1:]]
    stream = [dataclasses.replace(f, seq=i) for i, f in enumerate(stream)]
    results, _ = _run_session("kidnap", stream, robot)
    cut = len(pre)
    return {
        "robot": robot,
        "frames_before": cut,
        "frames_after": len(stream) - cut,
        "cut_s": cut_s,
        "jump_m": _jump(gt, pre[-1].stamp, first.stamp),
        **_after_cut(results, cut, gt),
    }


def _run_session(name: str, stream: list[FrameInput], seed: int) -> tuple[list[dict], int]:
    """Every frame of `stream` through a fresh uncapped MapSession: the frame results,
    and the live landmarks at the end."""
    config = {"landmark_cap": None, "seed": seed}
    with tempfile.TemporaryDirectory() as tmp:
        record = MapRecord("k", name, "mapping", config, time.time())
        session = MapSession.create(
            Path(tmp) / "k.sqlite", record, StoreSettings(snapshot_every=10_000)
        )
        results = [json.loads(session.submit(frame_to_dict(f)).result_json) for f in stream]
        live = len(session.slam.landmarks)
        session.close()
    return results, live


def _after_cut(results: list[dict], cut: int, gt: Any) -> dict[str, Any]:
    """What one robot's frame results show around its cut (frame index `cut`): ATE
    before, false `lost` events before, frames until `lost` and `relocalised`, ATE after."""
    statuses = [r["localisation"]["status"] for r in results]
    lost = next((k for k in range(cut, len(statuses)) if statuses[k] == "lost"), None)
    reloc = next((k for k in range(cut, len(statuses)) if statuses[k] == "relocalised"), None)
    return {
        "ate_before_m": _ate_of_results(results[:cut], gt),
        "lost_events_before_cut": sum(
            1 for k in range(1, cut) if statuses[k] == "lost" and statuses[k - 1] != "lost"
        ),
        "frames_to_lost": None if lost is None else lost - cut,
        "frames_to_relocalised": None if reloc is None else reloc - cut,
        "seconds_to_relocalised": None
        if reloc is None
        else results[reloc]["stamp"] - results[cut]["stamp"],
        "ate_after_relocalised_m": None if reloc is None else _ate_of_results(results[reloc:], gt),
        "status_counts_after_cut": {s: statuses[cut:].count(s) for s in set(statuses[cut:])},
    }


def _lost_events(statuses: list[str]) -> int:
    """How often a robot became `lost` (runs of `lost` frames)."""
    return sum(1 for k in range(1, len(statuses)) if statuses[k] == "lost" != statuses[k - 1])


def tracking_service(directory: Path, robot: int) -> dict[str, Any]:
    """One robot's whole run, no kidnap, through a fresh MapSession: a `lost` here is a
    false alarm (the robot was never moved)."""
    frames, gt = mrclam_frames(load_mrclam(directory, robot))
    results, _ = _run_session("tracking", frames, robot)
    statuses = [r["localisation"]["status"] for r in results]
    return {
        "robot": robot,
        "frames": len(frames),
        "lost_events": _lost_events(statuses),
        "lost_frames": statuses.count("lost"),
        "ate_m": _ate_of_results(results, gt),
    }


def kidnap_shared(
    directory: Path, robot: int, before_s: float, cut_s: float, after_s: float
) -> dict[str, Any]:
    """As `kidnap`, in a map the five robots build together: every robot's frames of the
    first `before_s` seconds (interleaved by stamp, each from its initial pose), then
    robot N alone after its 60 s cut. Robot N then lands among landmarks the others
    mapped, which is what makes a kidnap observable at all."""
    runs = {r: mrclam_frames(load_mrclam(directory, r)) for r in range(1, 6)}
    frames, gt = runs[robot]
    t0 = frames[0].stamp
    t_cut = t0 + before_s
    pre = [f for r, (fr, _) in runs.items() for f in fr if f.stamp < t_cut]
    pre.sort(key=lambda f: (f.stamp, f.robot))
    post = [f for f in frames if t_cut + cut_s <= f.stamp < t_cut + cut_s + after_s]
    jump = dataclasses.replace(post[0], odometry=Odometry(0.0, 0.0, 0.0))
    seq: dict[str, int] = {}
    stream = []
    for f in [*pre, jump, *post[1:]]:
        seq[f.robot] = seq.get(f.robot, -1) + 1
        stream.append(dataclasses.replace(f, seq=seq[f.robot]))
    name = frames[0].robot
    results, live = _run_session("kidnap-shared", stream, robot)
    mine = [r for r in results if r["robot"] == name]
    cut = sum(1 for f in pre if f.robot == name)
    landmarks_at_cut = next((r["landmarks"]["live"] for r in reversed(results[: len(pre)])), None)

    return {
        "robot": robot,
        "frames_before": cut,
        "frames_of_all_robots_before": len(pre),
        "landmarks_at_cut": landmarks_at_cut,
        "landmarks_at_end": live,
        "frames_after": len(mine) - cut,
        "jump_m": _jump(gt, pre[-1].stamp, post[0].stamp),
        **_after_cut(mine, cut, gt),
    }


def kidnap_localiser(
    directory: Path, robot: int, before_s: float, cut_s: float, after_s: float, seed: int
) -> dict[str, Any]:
    """The localiser alone on the surveyed map: tracking from the true first pose, then
    the cut. Frames until the filter is converged within 0.5 m and 15 deg of the truth
    again ("recovered": augmented MCL may recover without the status ever leaving
    `tracking`), until `lost` and `relocalised` if it got there; ATE afterwards."""
    data = load_mrclam(directory, robot)
    assert data.landmarks is not None
    landmarks = {str(int(s)): np.array([x, y]) for s, x, y in data.landmarks}
    frames, gt = mrclam_frames(data)
    t0 = frames[0].stamp
    pre = [f for f in frames if f.stamp < t0 + before_s]
    post = [f for f in frames if t0 + before_s + cut_s <= f.stamp < t0 + before_s + cut_s + after_s]
    loc = Localiser(LocaliserConfig(learn_places=False))
    rng = np.random.default_rng([seed, robot])
    statuses: list[str] = []
    converged: list[bool] = []
    errors: list[tuple[float, float]] = []
    stream = [*pre, *post]
    for k, f in enumerate(stream):
        odo = None
        if 0 < k != len(pre) and f.odometry is not None:
            odo = (f.odometry.dx, f.odometry.dy, f.odometry.dtheta)
        truth = _truth_at(gt, f.stamp)
        start = None
        if k == 0:
            assert truth is not None
            start = (truth, np.diag([1e-4, 1e-4, 1e-4]))
        res = loc.step(
            "r",
            odometry=odo,
            dt_s=0.0 if k == 0 else max(f.stamp - stream[k - 1].stamp, 0.0),
            labels=[o.label for o in f.observations],
            bearings_rad=[o.bearing_rad for o in f.observations],
            sigmas_rad=[o.sigma_rad for o in f.observations],
            landmarks=landmarks,
            graph_pose=start,
            rng=rng,
        )
        statuses.append(res.status)
        converged.append(res.estimate.converged)
        errors.append(
            _errors(res.estimate.pose_xytheta, truth) if truth is not None else (math.nan,) * 2
        )
    cut = len(pre)
    lost = next((k for k in range(cut, len(stream)) if statuses[k] == "lost"), None)
    reloc = next((k for k in range(cut, len(stream)) if statuses[k] == RELOCALISED), None)
    recovered = next(
        (
            k
            for k in range(cut, len(stream))
            if converged[k] and errors[k][0] <= 0.5 and errors[k][1] <= math.radians(15)
        ),
        None,
    )
    after = np.array([e[0] for e in errors[reloc:] if not math.isnan(e[0])]) if reloc else None
    since = (
        np.array([e[0] for e in errors[recovered:] if not math.isnan(e[0])]) if recovered else None
    )
    return {
        "robot": robot,
        "frames_before": cut,
        "jump_m": _jump(gt, pre[-1].stamp, post[0].stamp),
        "lost_events_before_cut": sum(
            1 for k in range(1, cut) if statuses[k] == "lost" and statuses[k - 1] != "lost"
        ),
        "ate_before_cut_m": float(np.sqrt(np.nanmean(np.square([e[0] for e in errors[:cut]])))),
        "error_after_cut_m": errors[cut][0],
        "frames_to_recovered": None if recovered is None else recovered - cut,
        "seconds_to_recovered": None
        if recovered is None
        else stream[recovered].stamp - post[0].stamp,
        "ate_after_recovered_m": None
        if since is None or not len(since)
        else float(np.sqrt(np.mean(since**2))),
        "frames_to_lost": None if lost is None else lost - cut,
        "frames_to_relocalised": None if reloc is None else reloc - cut,
        "seconds_to_relocalised": None if reloc is None else stream[reloc].stamp - post[0].stamp,
        "error_at_relocalised_m": None if reloc is None else errors[reloc][0],
        "error_at_relocalised_deg": None if reloc is None else math.degrees(errors[reloc][1]),
        "ate_after_relocalised_m": None
        if after is None or not len(after)
        else float(np.sqrt(np.mean(after**2))),
    }


# --------------------------------------------------------------------------- main
def plot(doc: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    t = doc["pf_timing"]
    axes[0].bar([str(r["particles"]) for r in t], [r["update_ms_median"] for r in t])
    axes[0].axhline(0.5, color="r", ls="--", label="goal 0.5 ms (1000 x 32)")
    axes[0].set_xlabel("particles (32 landmarks)")
    axes[0].set_ylabel("PF update, median ms")
    axes[0].legend()
    g = doc["global"]
    frames = [r["frames_to_relocalise"] for r in g["runs"] if r["success"]]
    axes[1].hist(frames, bins=20)
    axes[1].set_xlabel("frames to relocalised (successful starts)")
    axes[1].set_title(
        f"MRCLAM-6 global localisation: {100 * g['success_rate']:.0f} % of {g['starts']}"
    )
    errs = [r["error_m"] for r in g["runs"] if r["frames_to_relocalise"] is not None]
    axes[2].hist(np.minimum(errs, 3.0), bins=30)
    axes[2].axvline(0.5, color="r", ls="--")
    axes[2].set_xlabel("position error at relocalisation, m (clipped at 3)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


_BY_MAPPER = (
    "success_rate",
    "wrong_convergence_rate",
    "median_frames_to_success",
    "median_frames_to_information",
    "ratio_of_medians",
    "map_admits_success_rate",
    "success_where_map_admits",
    "information_reached",
    "information_reached_ekf",
)


def _by_mapper(doc: dict[str, Any], mappers: list[int]) -> dict[str, Any]:
    """One row per mapper of the online part's figures: the map's error after the fit
    and its scale, and the starts' summary."""
    rows = {}
    for mapper in mappers:
        run = doc[f"online_mapper_{mapper}"]
        built = run["map"]
        rows[str(mapper)] = {
            "landmarks": built["landmarks"],
            "landmark_rmse_in_map_frame_m": built["landmark_rmse_in_map_frame_m"],
            "landmark_similarity_scale": built["landmark_similarity_scale"],
            "frame_rotation_deg": built["frame_rotation_deg"],
            **{k: run.get(k) for k in _BY_MAPPER},
            "wrong_within_map_implied": sum(
                1 for w in run["wrong_convergences"] if w.get("within_of_map_implied")
            ),
            "wrong_convergences": len(run["wrong_convergences"]),
        }
    return rows


def _window_config(args: argparse.Namespace) -> WindowCheckConfig | None:
    """The check the flags ask for, or None (the map's own)."""
    sigma, stable = args.window_landmark_sigma, args.window_stable_frames
    if sigma is None and stable is None:
        return None
    return WindowCheckConfig(landmark_sigma_m=sigma or 0.0, stable_frames=stable or 0)


def _stamp() -> dict[str, Any]:
    """When a part ran and the machine's load then (a shared machine: timings vary)."""
    return {
        "when": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "load_average": [round(v, 2) for v in os.getloadavg()],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--starts", type=int, default=50)
    parser.add_argument("--max-frames", type=int, default=150)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--other-seeds",
        type=int,
        nargs="*",
        default=[1, 2, 3],
        help="global localisation again with these seeds (other starts, other filter draws): "
        "summaries only, to show the spread of the figures",
    )
    parser.add_argument("--kidnap-robots", type=int, nargs="*", default=[1, 2, 3, 4, 5])
    parser.add_argument(
        "--parts",
        nargs="*",
        choices=[
            "pf",
            "global",
            "check",
            "study",
            "bound",
            "online",
            "online-kidnap",
            "online-swap",
            "online-tracking",
            "kidnap",
            "tracking",
        ],
        default=["pf", "global", "kidnap"],
        help="parts to run; the others keep their figures from an existing localisation.json",
    )
    parser.add_argument("--mapper", type=int, default=1, help="online: the robot that maps")
    parser.add_argument(
        "--mappers",
        type=int,
        nargs="*",
        default=None,
        help="online: each of these robots maps in turn (figures under online_mapper_<N>, "
        "a table of them under online_mappers)",
    )
    parser.add_argument("--online-starts", type=int, default=5, help="online: starts per robot")
    parser.add_argument("--online-seeds", type=int, nargs="*", default=[0, 1])
    parser.add_argument(
        "--online-key", default=None, help="online: the key its figures go under (online)"
    )
    parser.add_argument("--no-bound", action="store_true", help="online: skip the bound")
    parser.add_argument(
        "--online-map",
        choices=MAP_SOURCES,
        default="session",
        help="online: the map the starts enter (see MAP_SOURCES); figures under "
        "online_<this>_map unless --online-key is given",
    )
    parser.add_argument(
        "--window-landmark-sigma",
        type=float,
        default=None,
        help="online: the check's landmark sigma, m (WindowCheckConfig.landmark_sigma_m)",
    )
    parser.add_argument(
        "--window-stable-frames",
        type=int,
        default=None,
        help="online: frames the check's solution must hold (WindowCheckConfig.stable_frames)",
    )
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    parser.add_argument("--data", type=Path, default=None)
    args = parser.parse_args()
    directory = args.data or default_mrclam_dir()
    path = args.out / "localisation.json"
    doc: dict[str, Any] = json.loads(path.read_text()) if path.exists() else {}
    doc["machine"] = {"platform": platform.platform(), "cpus": os.cpu_count()}
    runs = doc.setdefault("runs_of_parts", {})
    if "when" in doc:  # a document from before parts: all of it ran then
        old = doc.pop("when")
        for part in ("pf", "global", "kidnap"):
            runs.setdefault(part, {"when": old})
    if "pf" in args.parts:
        doc["runs_of_parts"]["pf"] = _stamp()
        doc["pf_timing"] = [pf_timing(1000), pf_timing(5000)]
        doc["runs_of_parts"]["pf"]["load_average_after"] = [round(v, 2) for v in os.getloadavg()]
        print(json.dumps(doc["pf_timing"], indent=1), doc["runs_of_parts"]["pf"])
    if "global" in args.parts:
        doc["runs_of_parts"]["global"] = _stamp()
        doc["global"] = global_localisation(directory, args.starts, args.max_frames, args.seed)
        print({k: v for k, v in doc["global"].items() if k != "runs"})
        doc["global_other_seeds"] = []
        for seed in args.other_seeds:
            other = global_localisation(directory, args.starts, args.max_frames, seed)
            doc["global_other_seeds"].append(
                {"seed": seed, **{k: v for k, v in other.items() if k not in ("runs", "map")}}
            )
            print(doc["global_other_seeds"][-1])
    if "check" in args.parts:
        doc["runs_of_parts"]["check"] = _stamp()
        seeds = [args.seed, *args.other_seeds]
        doc["global_window_check"] = global_check_study(
            directory, args.starts, args.max_frames, seeds
        )
    if "study" in args.parts:
        doc["runs_of_parts"]["study"] = _stamp()
        seeds = [args.seed, *args.other_seeds[:1]]
        doc["global_study"] = global_study(directory, args.starts, args.max_frames, seeds)
        for name, row in doc["global_study"].items():
            print(name, row["runs"])
    if "bound" in args.parts:
        doc["runs_of_parts"]["bound"] = _stamp()
        seeds = [args.seed, *args.other_seeds]
        doc["information_bound"] = information_bound(
            directory, args.starts, args.max_frames, seeds, doc
        )
        print(json.dumps({k: v for k, v in doc["information_bound"].items() if k != "runs"}))
    if "online" in args.parts:
        key = args.online_key or (
            "online" if args.online_map == "session" else f"online_{args.online_map}_map"
        )
        mappers = args.mappers or [args.mapper]
        for mapper in mappers:
            at = f"online_mapper_{mapper}" if args.mappers else key
            doc["runs_of_parts"][at] = _stamp()
            online = online_localisation(
                directory,
                mapper,
                args.online_starts,
                args.max_frames,
                args.online_seeds,
                bound=not args.no_bound,
                source=args.online_map,
                window=_window_config(args),
            )
            online["runs"] = {
                "n": len(online["runs"]),
                "per_item": "not kept (regenerated by the bench; wrong_convergences lists those)",
            }
            doc[at] = online
            print(json.dumps(online))
        if args.mappers:
            doc["online_mappers"] = _by_mapper(doc, mappers)
            print(json.dumps(doc["online_mappers"]))
    if "online-kidnap" in args.parts:
        doc["runs_of_parts"]["online_kidnap"] = _stamp()
        doc["online_kidnap"] = online_kidnap(directory, args.mapper, 120.0, 60.0, 120.0)
    if "online-swap" in args.parts:
        doc["runs_of_parts"]["online_swap"] = _stamp()
        doc["online_swap"] = online_kidnap(directory, args.mapper, 120.0, 0.0, 120.0, swap=True)
    if "online-tracking" in args.parts:
        doc["runs_of_parts"]["online_tracking"] = _stamp()
        doc["online_tracking"] = online_tracking(directory, args.mapper)
    if "kidnap" in args.parts:
        doc["runs_of_parts"]["kidnap"] = _stamp()
        doc["kidnap_localiser"] = [
            kidnap_localiser(directory, r, 120.0, 60.0, 120.0, args.seed)
            for r in args.kidnap_robots
        ]
        for row in doc["kidnap_localiser"]:
            print(row)
        doc["kidnap_service"] = [
            kidnap(directory, r, 120.0, 60.0, 120.0) for r in args.kidnap_robots
        ]
        for row in doc["kidnap_service"]:
            print(row)
        doc["kidnap_shared_map"] = [
            kidnap_shared(directory, r, 120.0, 60.0, 120.0) for r in args.kidnap_robots
        ]
        for row in doc["kidnap_shared_map"]:
            print(row)
    if "tracking" in args.parts:
        doc["runs_of_parts"]["tracking"] = _stamp()
        doc["tracking_service"] = [tracking_service(directory, r) for r in args.kidnap_robots]
        for row in doc["tracking_service"]:
            print(row)
    args.out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1))
    if {"pf_timing", "global"} <= set(doc) and isinstance(doc["global"].get("runs"), list):
        plot(doc, args.out / "localisation.png")


if __name__ == "__main__":
    main()
