"""Lifelong run: do covslam's time per frame and memory stay flat over 20 000 frames?

Run from the repository root::

    python -m bench.lifelong [--frames 20000] [--baseline-frames N]
                             [--baseline-budget-s 900] [--out bench/results]

One deterministic simulated run (``service.offline.datasets.indoor_sim``: 3x3 rooms, 225
landmarks, fixed seed) is fed through two estimators, each in its own fresh
child process (``--worker``, started with ``subprocess``) so that one run's
memory cannot show up in the other's RSS:

``bounded``
    ``SlamConfig(landmark_cap=50, policy="coverage")`` (the default 100-pose window)
    over every frame.
``baseline``
    plain uncapped iSAM2, ``SlamConfig(landmark_cap=None, pose_window=None)``,
    over the same frames until ``--baseline-frames`` frames are done or
    ``--baseline-budget-s`` seconds of wall time are spent, whichever first.

The child's loop is that of ``service.offline.replay.replay`` (same map seed, no pose
covariance, ``perf_counter`` around ``BearingSlam.process``, current RSS every
100 frames) plus the per-stage timings of ``FrameOutcome.timing_ms``, the
wall-time budget, and a clean stop (reported) if the estimator raises.

Figures, for N frames (N = 20 000 by default): median ms/frame over the early
window [N/20, N/10) and the late window [0.95 N, N) and their ratio (goal <=
1.1); the process's peak RSS at frame N/4 against its peak RSS at frame N (growth
goal <= 5 %; Linux's peak counter is reset at N/4, so the two halves' peaks are
both known), with the stricter reading beside it (the current RSS at N/4 against
the peak from N/4 on); live-landmark statistics; removals; ATE RMSE against
ground truth; the median ms/frame of every N/20-frame checkpoint window for both
runs; and the ratio baseline / bounded at the last checkpoint window both reached
(goal >= 10 by the end). If the baseline stops early, the JSON says where
(``baseline_truncated_at_frame``) and the ratio is the one at the furthest window
it reached; a power-law fit carried to the late window is given only under a key
that says it is an extrapolation.

``--world dense`` drives the same world with every landmark of the room within 6 m
in view (``indoor_sim.DENSE_OBSERVATIONS``: ~25 bearings a frame instead of ~10).

Tail: per block of 1 000 frames, the median, 99th percentile and maximum ms a frame and
their ratios (goals: p99 <= 4x and max <= 20x the block's median).

The children limit numpy's BLAS to ``--blas-threads`` threads (default 1, as the
service's workers do): on a loaded machine a multi-threaded BLAS makes the frames that
factor a large dense marginal ~10x slower, and the tail with them.

Writes ``<out>/lifelong[_dense].json`` and ``<out>/lifelong[_dense].png``; prints a
summary.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import hashlib
import importlib.metadata
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from array import array
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from graph.config import SlamConfig
from service.offline.datasets.indoor_sim import DENSE_OBSERVATIONS, SimRun, make_world, simulate
from service.offline.evaluation import Trajectory, ate_rmse
from service.offline.replay import (
    current_rss_mb,
    peak_rss_mb,
    reset_peak_rss,
    spooled_map,
)

SEED = 20_240
"""Seed of the world, the run and both maps' rngs (fixed so every run is the same)."""
ROOMS = (3, 3)
LANDMARKS = 225
ROBOT = "r1"
RSS_EVERY = 100
"""Frames between RSS samples (as ``replay``'s default)."""
SERIES_EVERY = 100
"""Frames per block of the down-sampled series written to the JSON."""
ROLLING = 100
"""Frames of the trailing rolling median in the plot."""
STAGES = ("prepare", "update", "budget", "covariance")
RUNS: dict[str, SlamConfig] = {
    "bounded": SlamConfig(landmark_cap=50, policy="coverage"),
    "baseline": SlamConfig(landmark_cap=None, pose_window=None),
}
TIME_RATIO_GOAL = 1.1
TAIL_BLOCK = 1000
TAIL_P99_GOAL = 4.0
TAIL_MAX_GOAL = 20.0
WORLDS: dict[str, dict[str, Any]] = {"standard": {}, "dense": DENSE_OBSERVATIONS}
RSS_GROWTH_GOAL_PCT = 5.0
BASELINE_SLOWDOWN_GOAL = 10.0
REPO = Path(__file__).resolve().parent.parent

FloatArray = NDArray[np.float64]


# --------------------------------------------------------------------------- the run
def make_run(frames: int, seed: int, world: str = "standard") -> SimRun:
    """The simulated run: one rng, world first, then the drive (`world`: see WORLDS)."""
    rng = np.random.default_rng(seed)
    rooms = make_world(rooms=ROOMS, landmarks=LANDMARKS, rng=rng)
    return simulate(rooms, frames=frames, rng=rng, robot=ROBOT, **WORLDS[world])


def run_digest(run: SimRun) -> str:
    """Short hash of the ground truth, to check both children saw the same frames."""
    h = hashlib.sha256(np.ascontiguousarray(run.ground_truth.poses()).tobytes())
    h.update(np.ascontiguousarray(run.landmarks).tobytes())
    return h.hexdigest()[:16]


def windows(n: int) -> dict[str, tuple[int, int]]:
    """The early and late windows [lo, hi) of an n-frame run."""
    return {"early": (n // 20, n // 10), "late": (n - n // 20, n)}


def checkpoint_step(n: int) -> int:
    return max(1, n // 20)


# --------------------------------------------------------------------------- child
_PROBE_MATRIX = np.random.default_rng(0).standard_normal((200, 200))
_PROBE_SPD = _PROBE_MATRIX @ _PROBE_MATRIX.T + 200.0 * np.eye(200)


def speed_probe_ms() -> float:
    """Wall ms of a fixed workload that allocates nothing lasting: a pure-Python loop
    and dense Cholesky factorisations, the two kinds of work a frame does (the
    estimator's Python bookkeeping, GTSAM's dense eliminations). Measured beside the
    run, it tells the machine's speed from the code's: a core that slows down (another
    job, its clock) slows the probe too, and a frame whose cost grew does not."""
    t0 = time.perf_counter()
    _ = sum(i & 7 for i in range(600_000))
    for _ in range(150):
        np.linalg.cholesky(_PROBE_SPD)
    return 1e3 * (time.perf_counter() - t0)


def perturb_heap(seed: int) -> list[bytearray]:
    """Allocate 5-40 buffers of up to 300 kB and free every other one, so the run starts
    from a different heap layout (< 6 MB kept). The computation stays the same; what
    changes is where glibc places and reuses the dense blocks of the run, which moves
    its RSS transients: repeated with several seeds, it shows how much of the peak-RSS
    reading is the heap's history rather than the estimator. The caller holds what it
    returns for the run's lifetime."""
    rng = np.random.default_rng(seed)
    buffers = [bytearray(int(rng.integers(1, 300_000))) for _ in range(int(rng.integers(5, 41)))]
    return buffers[1::2]


def run_worker(
    name: str,
    frames: int,
    seed: int,
    max_frames: int,
    budget_s: float | None,
    out: Path,
    release_heap: bool = True,
    world: str = "standard",
    blas_threads: int = 1,
    settings: dict[str, Any] | None = None,
) -> None:
    """Process the run through one configuration (with `settings` changed: SlamConfig
    fields); write per-frame data to `out` (JSON)."""
    if blas_threads:
        threadpool_limits(limits=blas_threads, user_api="blas")
    run = make_run(frames, seed, world)
    digest = run_digest(run)
    todo = run.frames[:max_frames]
    del run
    config = dataclasses.replace(RUNS[name], **(settings or {}))
    load_start = os.getloadavg()
    rss_before = current_rss_mb()
    result = spooled_map(config, seed, release_heap=release_heap)
    slam = result.slam
    # Per-frame figures in typed arrays (8 bytes a number, not a list's ~32), allocated
    # whole before the first frame: the run's own bookkeeping is inside the RSS it
    # measures, and arrays that grew with the frames put their growth (~0.5 MiB from
    # frame 2 500 to 10 000, 0.3 % of the peak) into the product's figure.
    n_todo = len(todo)
    stages: dict[str, array[float]] = {k: _zeros("d", n_todo) for k in STAGES}
    frame_ms: array[float] = _zeros("d", n_todo)
    upkeep_ms: array[float] = _zeros("d", n_todo)
    cpu_ms: array[float] = _zeros("d", n_todo)
    live: array[int] = _zeros("i", n_todo)
    count = 0
    added = restored = 0
    step = checkpoint_step(frames)
    peak_reset_frame: int | None = None
    peak_before_reset: float | None = None
    stop = "all requested frames" if max_frames >= frames else "--baseline-frames limit"
    error = None
    probes: list[tuple[int, float]] = [(0, min(speed_probe_ms() for _ in range(3)))]
    held: list[tuple[int, int]] = []
    keyframes: list[tuple[int, int]] = []
    start = time.perf_counter()
    for frame in todo:
        if budget_s is not None and time.perf_counter() - start >= budget_s:
            stop = f"wall-time budget of {budget_s:g} s"
            break
        t0 = time.perf_counter()
        c0 = time.process_time()
        try:
            outcome = slam.process(frame, with_covariance=False)
            t1 = time.perf_counter()
            slam.upkeep()  # what a worker does once the frame's result is sent
        except Exception as exc:  # report how far it got, do not lose the run
            error = f"{type(exc).__name__}: {exc}"
            stop = "estimator error"
            break
        frame_ms[count] = 1e3 * (t1 - t0)
        upkeep_ms[count] = 1e3 * (time.perf_counter() - t1)
        cpu_ms[count] = 1e3 * (time.process_time() - c0)
        live[count] = len(slam.landmarks)  # after the upkeep: what the cap bounds
        added += len(outcome.added)
        restored += len(outcome.restored)
        for key in STAGES:
            stages[key][count] = outcome.timing_ms[key]
        count += 1
        done = slam.frame_count
        if done == frames // 4:
            # The goal is the peak from frame N/4 on: peaks before it do not count.
            peak_before_reset = peak_rss_mb()
            peak_reset_frame = done if reset_peak_rss() else None
        if done % RSS_EVERY == 0:
            result.rss_mb.append((done, current_rss_mb()))
            held.append((done, slam.held_trajectory_rows))
            keyframes.append((done, slam.keyframe_count))
        if done % step == 0:
            probes.append((done, min(speed_probe_ms() for _ in range(3))))
            median = np.median(frame_ms[count - step : count])
            print(
                f"[{name}] frame {done:6d}  median {median:8.2f} ms"
                f"  live {outcome.live:4d}  rss {current_rss_mb():7.1f} MiB"
                f"  {time.perf_counter() - start:7.1f} s",
                file=sys.stderr,
                flush=True,
            )
    wall_s = time.perf_counter() - start
    if error is None:
        slam.settle()  # the last upkeep's final trajectory rows, to the pose log
    peak = peak_rss_mb()
    rss_end = current_rss_mb()
    load_end = os.getloadavg()
    traj = result.trajectory(ROBOT).poses().tolist() if count else []
    record = {
        "name": name,
        "config": _config_dict(config),
        "digest": digest,
        "frames_done": count,
        "stop_reason": stop,
        "error": error,
        "wall_s": wall_s,
        "rss_before_mb": rss_before,
        "rss_end_mb": rss_end,
        "peak_rss_mb": peak,
        "peak_rss_since_frame": peak_reset_frame,
        "peak_rss_before_reset_mb": peak_before_reset,
        "release_heap": release_heap,
        "loadavg_start": load_start,
        "loadavg_end": load_end,
        "git_commit": machine_info()["git_commit"],
        "frame_ms": frame_ms[:count].tolist(),
        "upkeep_ms": upkeep_ms[:count].tolist(),
        "cpu_ms": cpu_ms[:count].tolist(),
        "stage_ms": {k: v[:count].tolist() for k, v in stages.items()},
        "live_landmarks": live[:count].tolist(),
        "speed_probe_ms": probes,
        "rss_mb": result.rss_mb,
        "removals": slam.removal_count,
        "landmarks_added": added,
        "landmarks_restored": restored,
        "first_removal_frame": result.removal_log.first_frame,
        "held_trajectory_rows": held,
        "keyframes": keyframes,
        # Every frame has one row: held by the estimator, or spooled.
        "spooled_trajectory_rows": slam.frame_count - slam.held_trajectory_rows,
        "trajectory": traj,
    }
    out.write_text(json.dumps(record))


def _zeros(typecode: str, n: int) -> array[Any]:
    """A typed array of `n` zeros, allocated in one piece."""
    return array(typecode, bytes(array(typecode).itemsize * n))


def _config_dict(config: SlamConfig) -> dict[str, Any]:
    return {name: getattr(config, name) for name in config.__slots__}


def spawn(
    name: str,
    frames: int,
    seed: int,
    max_frames: int,
    budget_s: float | None,
    world: str = "standard",
    blas_threads: int = 1,
    settings: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Run one configuration in a fresh child process and read its JSON back."""
    with tempfile.TemporaryDirectory(prefix="lifelong-") as tmp:
        out = Path(tmp) / f"{name}.json"
        cmd = [
            sys.executable,
            "-m",
            "bench.lifelong",
            "--worker",
            name,
            "--frames",
            str(frames),
            "--seed",
            str(seed),
            "--worker-max-frames",
            str(max_frames),
            "--worker-out",
            str(out),
            "--world",
            world,
            "--blas-threads",
            str(blas_threads),
            "--bounded-config",
            json.dumps(settings or {}),
        ]
        if budget_s is not None:
            cmd += ["--worker-budget-s", str(budget_s)]
        print(f"--- {name}: child process {' '.join(cmd[1:5])} ...", flush=True)
        proc = subprocess.run(cmd, cwd=REPO, check=False)
        if proc.returncode != 0 or not out.exists():
            return {"name": name, "crashed": True, "returncode": proc.returncode}
        record: dict[str, Any] = json.loads(out.read_text())
        return record


# --------------------------------------------------------------------------- figures
def window_median(ms: Sequence[float], lo: int, hi: int) -> float | None:
    """Median of frames [lo, hi), or None if the run did not complete the window."""
    if len(ms) < hi or hi <= lo:
        return None
    return float(np.median(ms[lo:hi]))


def checkpoints(record: dict[str, Any], n: int) -> list[dict[str, Any]]:
    """Median ms (total and per stage) of every complete N/20-frame window."""
    step = checkpoint_step(n)
    ms = record["frame_ms"]
    rows = []
    for end in range(step, len(ms) + 1, step):
        row: dict[str, Any] = {
            "frames": [end - step, end],
            "median_ms": round(float(np.median(ms[end - step : end])), 3),
            "p90_ms": round(float(np.percentile(ms[end - step : end], 90)), 3),
        }
        for key in STAGES:
            stage = record["stage_ms"][key][end - step : end]
            row[f"median_{key}_ms"] = round(float(np.median(stage)), 3)
        row["live_landmarks_at_end"] = record["live_landmarks"][end - 1]
        rows.append(row)
    return rows


def tail_figures(ms: Sequence[float], block: int = TAIL_BLOCK) -> dict[str, Any]:
    """Per complete block of `block` frames: median, p99 and max ms a frame and the two
    ratios to the median; the worst block's ratios against the goals."""
    rows: list[dict[str, Any]] = []
    ratios: list[tuple[float, float]] = []
    for lo in range(0, len(ms) - block + 1, block):
        part = np.asarray(ms[lo : lo + block])
        med = float(np.median(part))
        p99, top = float(np.percentile(part, 99)), float(part.max())
        ratios.append((p99 / med, top / med))
        rows.append(
            {
                "frames": [lo, lo + block],
                "median_ms": _r(med),
                "p99_ms": _r(p99),
                "max_ms": _r(top),
                "p99_over_median": _r(p99 / med, 2),
                "max_over_median": _r(top / med, 2),
            }
        )
    worst_p99 = max((r[0] for r in ratios), default=None)
    worst_max = max((r[1] for r in ratios), default=None)
    return {
        "block_frames": block,
        "blocks": rows,
        "worst_p99_over_median": _r(worst_p99, 2),
        "worst_max_over_median": _r(worst_max, 2),
        "p99_goal_max": TAIL_P99_GOAL,
        "max_goal_max": TAIL_MAX_GOAL,
        "p99_goal_met": None if worst_p99 is None else worst_p99 <= TAIL_P99_GOAL,
        "max_goal_met": None if worst_max is None else worst_max <= TAIL_MAX_GOAL,
    }


def rss_at(record: dict[str, Any], frame: int) -> tuple[int, float] | None:
    """The first RSS sample at or after `frame`."""
    for f, mb in record["rss_mb"]:
        if f >= frame:
            return int(f), float(mb)
    return None


def live_stats(live: Sequence[int], cap: int | None, skip: int) -> dict[str, Any]:
    arr = np.asarray(live[skip:] if len(live) > skip else live)
    out: dict[str, Any] = {
        "from_frame": skip if len(live) > skip else 0,
        "min": int(arr.min()),
        "max": int(arr.max()),
        "mean": round(float(arr.mean()), 2),
        "median": float(np.median(arr)),
        "final": int(live[-1]),
    }
    if cap is not None:
        out["fraction_of_frames_at_cap"] = round(float(np.mean(arr == cap)), 4)
        out["ever_above_cap_after_frame"] = bool(np.any(arr > cap))
    return out


def ate(record: dict[str, Any], gt: Trajectory, frames: int | None = None) -> dict[str, Any]:
    poses = np.asarray(record["trajectory"], dtype=np.float64)
    if frames is not None:
        poses = poses[:frames]
    if len(poses) < 2:
        return {"frames": len(poses), "ate_rmse_m": None, "ate_rmse_aligned_m": None}
    est = Trajectory.from_poses(gt.stamps[: len(poses)], poses)
    return {
        "frames": len(poses),
        "ate_rmse_m": round(ate_rmse(est, gt), 4),
        "ate_rmse_aligned_m": round(ate_rmse(est, gt, align=True), 4),
    }


def series(record: dict[str, Any]) -> dict[str, Any]:
    """Down-sampled per-frame data: block medians of ms, live count at block ends, RSS."""
    ms = record["frame_ms"]
    live = record["live_landmarks"]
    ends = list(range(SERIES_EVERY, len(ms) + 1, SERIES_EVERY))
    return {
        "block_frames": SERIES_EVERY,
        "frame": ends,
        "median_ms": [round(float(np.median(ms[e - SERIES_EVERY : e])), 3) for e in ends],
        "live_landmarks": [live[e - 1] for e in ends],
        "rss_mb": [[f, round(mb, 2)] for f, mb in record["rss_mb"]],
    }


def run_summary(record: dict[str, Any], n: int, gt: Trajectory) -> dict[str, Any]:
    """Figures common to both runs."""
    ms = np.asarray(record["frame_ms"])
    return {
        "config": record["config"],
        "frames_done": record["frames_done"],
        "stop_reason": record["stop_reason"],
        "error": record["error"],
        "wall_s": round(record["wall_s"], 1),
        "processing_s": round(float(ms.sum()) / 1e3, 1),
        "median_ms": round(float(np.median(ms)), 3) if ms.size else None,
        "mean_ms": round(float(ms.mean()), 3) if ms.size else None,
        "p99_ms": round(float(np.percentile(ms, 99)), 3) if ms.size else None,
        "max_ms": round(float(ms.max()), 3) if ms.size else None,
        "rss_before_run_mb": round(record["rss_before_mb"], 1),
        "rss_end_mb": round(record["rss_end_mb"], 1),
        "peak_rss_mb": round(record["peak_rss_mb"], 1),
        "peak_rss_since_frame": record.get("peak_rss_since_frame"),
        "peak_rss_before_reset_mb": _r(record.get("peak_rss_before_reset_mb"), 1),
        "release_heap": record.get("release_heap"),  # None: a record from before the option
        "removals": record["removals"],
        "landmarks_added": record.get("landmarks_added"),
        "landmarks_restored": record.get("landmarks_restored"),
        "first_removal_frame": record["first_removal_frame"],
        "live_landmarks": live_stats(
            record["live_landmarks"], record["config"]["landmark_cap"], n // 20
        ),
        "accuracy": ate(record, gt),
        "checkpoints": checkpoints(record, n),
        "git_commit": record.get("git_commit"),
        "loadavg_start": [round(x, 2) for x in record["loadavg_start"]],
        "loadavg_end": [round(x, 2) for x in record["loadavg_end"]],
        "series": series(record),
    }


def bounded_figures(record: dict[str, Any], n: int) -> dict[str, Any]:
    ms = record["frame_ms"]
    win = windows(n)
    early = window_median(ms, *win["early"])
    late = window_median(ms, *win["late"])
    ratio = late / early if early and late is not None else None
    # CPU time of the process: what the frame cost, whatever else the machine ran.
    cpu = record.get("cpu_ms", [])
    cpu_early = window_median(cpu, *win["early"])
    cpu_late = window_median(cpu, *win["late"])
    cpu_ratio = cpu_late / cpu_early if cpu_early and cpu_late is not None else None
    # The same ratio with each window's time divided by the speed probe measured at its
    # two ends (see speed_probe_ms): the frames' cost, the machine's speed taken out.
    probes = dict(record.get("speed_probe_ms", []))

    def probe(lo: int, hi: int) -> float | None:
        ends = [probes[k] for k in (lo, hi) if k in probes]
        return float(np.mean(ends)) if ends else None

    p_early, p_late = probe(*win["early"]), probe(*win["late"])
    speed_ratio = p_late / p_early if p_early and p_late else None
    normalised = ratio / speed_ratio if ratio is not None and speed_ratio else None
    quarter = rss_at(record, n // 4)
    peak = record["peak_rss_mb"]
    # The goal's reading: the process's peak RSS (ru_maxrss) at frame N/4 against the
    # same counter at frame N. The counter is reset at N/4, so the peak at N is the larger
    # of the two halves' peaks. Without a reset (a record from before it, or no
    # clear_refs) there is no peak at N/4, and the goal falls back to the stricter
    # reading below.
    early_peak = record.get("peak_rss_before_reset_mb")
    peak_growth = 100.0 * (max(peak, early_peak) - early_peak) / early_peak if early_peak else None
    # Stricter: the peak over N/4..N against the current RSS at N/4, which counts any
    # transient on top of the steady RSS as growth, however early such transients came.
    growth = 100.0 * (peak - quarter[1]) / quarter[1] if quarter else None
    growth_current = 100.0 * (record["rss_end_mb"] - quarter[1]) / quarter[1] if quarter else None
    creep = steady_rss_creep(record, n)
    held = [h for _, h in record.get("held_trajectory_rows", [])]
    keyframes = record.get("keyframes", [])
    goal_key, goal_growth = (
        ("peak_rss_growth_pct_end_vs_quarter", peak_growth)
        if peak_growth is not None
        else ("rss_growth_pct_peak_end_vs_quarter", growth)
    )
    return {
        "early_window": list(win["early"]),
        "late_window": list(win["late"]),
        "median_ms_early": _r(early),
        "median_ms_late": _r(late),
        "time_ratio_late_over_early": _r(ratio, 4),
        "time_ratio_goal_max": TIME_RATIO_GOAL,
        "time_ratio_goal_met": None if ratio is None else ratio <= TIME_RATIO_GOAL,
        "speed_probe_ms_early": _r(p_early),
        "speed_probe_ms_late": _r(p_late),
        "time_ratio_speed_normalised": _r(normalised, 4),
        "median_cpu_ms_early": _r(cpu_early),
        "median_cpu_ms_late": _r(cpu_late),
        "cpu_time_ratio_late_over_early": _r(cpu_ratio, 4),
        "rss_quarter_frame": quarter[0] if quarter else None,
        "rss_at_quarter_mb": _r(quarter[1] if quarter else None, 2),
        "peak_rss_end_mb": _r(peak, 2),
        "peak_rss_since_frame": record.get("peak_rss_since_frame"),
        "peak_rss_at_quarter_mb": _r(early_peak, 2),
        "peak_rss_growth_pct_end_vs_quarter": _r(peak_growth, 2),
        "rss_growth_pct_peak_end_vs_quarter": _r(growth, 2),
        "rss_growth_pct_current_end_vs_quarter": _r(growth_current, 2),
        "rss_growth_goal_reading": goal_key,
        "rss_growth_goal_max_pct": RSS_GROWTH_GOAL_PCT,
        "rss_growth_goal_met": (
            None if goal_growth is None else goal_growth <= RSS_GROWTH_GOAL_PCT
        ),
        "steady_rss_creep_bytes_per_frame": _r(creep, 1),
        "held_trajectory_rows_max": max(held) if held else None,
        # (frame, keyframes) at every tenth of the run: bounded by the area explored
        # (keyframe_placement "area") or by max_keyframes per robot ("spacing").
        "keyframes": [*keyframes[-1 :: -max(len(keyframes) // 10, 1)]][::-1],
        "spooled_trajectory_rows": record.get("spooled_trajectory_rows"),
        "tail": tail_figures(ms),
        # The same without each frame's budget stage (its removals, keyframe thinnings and
        # sparsifications; ~0 with upkeep "after_frame"). Not the goal's reading; it says
        # where the tail is.
        "tail_without_budget": tail_figures(
            np.asarray(ms) - np.asarray(record["stage_ms"]["budget"][: len(ms)])
        ),
        # With upkeep "after_frame": the worker's busy time per frame, the frame and its
        # upkeep (which runs once the frame's result is sent). The frame's answer waits
        # only for `tail`; the next frame waits for this when it comes sooner.
        **(upkeep_figures(ms, upkeep) if (upkeep := record.get("upkeep_ms")) else {}),
    }


def upkeep_figures(ms: Sequence[float], upkeep: Sequence[float]) -> dict[str, Any]:
    """The upkeeps' time and the tail of each frame's time with its upkeep."""
    up = np.asarray(upkeep[: len(ms)], dtype=np.float64)
    busy = np.asarray(ms, dtype=np.float64) + up
    return {
        "upkeep_ms_median": _r(float(np.median(up))),
        "upkeep_ms_p99": _r(float(np.percentile(up, 99))),
        "upkeep_ms_max": _r(float(up.max())),
        "tail_with_upkeep": tail_figures(busy.tolist()),
    }


def steady_rss_creep(record: dict[str, Any], n: int, block: int = 1000) -> float | None:
    """Slope of the steady RSS from frame N/4 on, bytes a frame: a least-squares line
    through the lowest RSS sample of each `block` frames (the transients above it, see
    the module docstring, are left out). None with fewer than three blocks."""
    samples = [(f, mb) for f, mb in record["rss_mb"] if f > n // 4]
    lows: dict[int, float] = {}
    for f, mb in samples:
        b = (f - 1) // block
        lows[b] = min(lows.get(b, mb), mb)
    if len(lows) < 3:
        return None
    blocks = np.array(sorted(lows), dtype=np.float64)
    slope_mb = np.polyfit(blocks * block, [lows[int(b)] for b in blocks], 1)[0]
    return float(slope_mb * 2**20)


def _cpu_slowdown(
    bounded: dict[str, Any], baseline: dict[str, Any], lo: int, hi: int
) -> float | None:
    """baseline / bounded median CPU ms over frames [lo, hi), if both recorded it."""
    b, p = bounded.get("cpu_ms", [])[lo:hi], baseline.get("cpu_ms", [])[lo:hi]
    if not b or not p:
        return None
    return _r(float(np.median(p)) / float(np.median(b)), 3)


def comparison(
    bounded: dict[str, Any], baseline: dict[str, Any], n: int, gt: Trajectory
) -> dict[str, Any]:
    """Baseline against bounded at the last checkpoint window both completed."""
    step = checkpoint_step(n)
    done = min(len(bounded["frame_ms"]), len(baseline["frame_ms"]))
    last_end = (done // step) * step
    truncated = len(baseline["frame_ms"]) < n
    out: dict[str, Any] = {
        "baseline_frames_done": len(baseline["frame_ms"]),
        "baseline_reached_end": not truncated,
        "baseline_truncated_at_frame": len(baseline["frame_ms"]) if truncated else None,
        "baseline_stop_reason": baseline["stop_reason"],
        "slowdown_goal_min": BASELINE_SLOWDOWN_GOAL,
    }
    if last_end == 0:
        out["note"] = "the baseline completed no checkpoint window"
        return out
    lo = last_end - step
    cpu = _cpu_slowdown(bounded, baseline, lo, last_end)
    b = float(np.median(bounded["frame_ms"][lo:last_end]))
    p = float(np.median(baseline["frame_ms"][lo:last_end]))
    out.update(
        {
            "last_common_window": [lo, last_end],
            "bounded_median_ms": _r(b),
            "baseline_median_ms": _r(p),
            "slowdown_baseline_over_bounded": _r(p / b, 3),
            "slowdown_cpu_time": cpu,
            "slowdown_goal_met_at_window": p / b >= BASELINE_SLOWDOWN_GOAL,
            # CPU time is what to compare when the two runs met different machine
            # load (wall time then measures the load as much as the estimator).
            "slowdown_goal_met_at_window_cpu_time": None
            if cpu is None
            else cpu >= BASELINE_SLOWDOWN_GOAL,
            "slowdown_is_at_end_of_run": not truncated,
            "accuracy_on_baseline_frames": {
                "frames": done,
                "bounded": ate(bounded, gt, done),
                "baseline": ate(baseline, gt, done),
            },
        }
    )
    if truncated:
        out["note"] = (
            f"baseline stopped at frame {done} ({baseline['stop_reason']}); the slowdown "
            f"is measured at window [{lo}, {last_end}), not at the end of the run"
        )
        out["EXTRAPOLATION_not_measured"] = extrapolate(baseline, n, b_late=bounded)
    return out


def extrapolate(baseline: dict[str, Any], n: int, b_late: dict[str, Any]) -> dict[str, Any] | None:
    """Power-law fit ms = a * frame^k of the baseline's checkpoint medians, carried to N.

    An extrapolation, labelled as such: iSAM2's cost need not follow a power law.
    """
    rows = checkpoints(baseline, n)[1:]  # the first window is start-up
    if len(rows) < 3:
        return None
    mid = np.array([0.5 * (r["frames"][0] + r["frames"][1]) for r in rows])
    med = np.array([r["median_ms"] for r in rows])
    k, log_a = np.polyfit(np.log(mid), np.log(med), 1)
    lo, hi = windows(n)["late"]
    at = float(np.exp(log_a) * (0.5 * (lo + hi)) ** k)
    late = window_median(b_late["frame_ms"], lo, hi)
    return {
        "label": "EXTRAPOLATED, NOT MEASURED",
        "method": "least-squares line in log(ms) vs log(frame) over checkpoint medians "
        f"{rows[0]['frames'][0]}..{rows[-1]['frames'][1]}",
        "exponent": round(float(k), 3),
        "baseline_median_ms_at_late_window": round(at, 2),
        "slowdown_at_late_window": None if not late else round(at / late, 2),
    }


def _r(x: float | None, digits: int = 3) -> float | None:
    return None if x is None else round(float(x), digits)


# --------------------------------------------------------------------------- output
def machine_info() -> dict[str, Any]:
    def version(pkg: str) -> str | None:
        try:
            return importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            return None

    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True, check=False
        ).stdout.strip()
        dirty = bool(
            subprocess.run(
                ["git", "status", "--porcelain", "--untracked-files=no"],
                cwd=REPO,
                capture_output=True,
                text=True,
                check=False,
            ).stdout.strip()
        )
    except OSError:
        commit, dirty = "", False
    return {
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "gtsam": version("gtsam"),
        "numpy": version("numpy"),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "git_commit": commit or None,
        "git_dirty_tracked_files": dirty,
    }


def rolling_median(ms: Sequence[float], window: int) -> tuple[FloatArray, FloatArray]:
    """(frame index at window end, trailing rolling median)."""
    arr = np.asarray(ms, dtype=np.float64)
    if len(arr) < window:
        return np.arange(1, len(arr) + 1, dtype=np.float64), arr
    med = np.median(np.lib.stride_tricks.sliding_window_view(arr, window), axis=1)
    return np.arange(window, len(arr) + 1, dtype=np.float64), med


def plot(records: dict[str, dict[str, Any]], n: int, seed: int, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = {"bounded": "tab:blue", "baseline": "tab:red"}
    labels = {
        "bounded": "covslam bounded (cap 50, coverage, 100-pose window)",
        "baseline": "plain iSAM2 (no cap, every pose kept)",
    }
    fig, axes = plt.subplots(3, 1, figsize=(10, 11), sharex=True)
    ax_ms, ax_rss, ax_live = axes
    for name, rec in records.items():
        if rec.get("crashed") or not rec["frame_ms"]:
            continue
        x, med = rolling_median(rec["frame_ms"], ROLLING)
        ax_ms.plot(x, med, color=colours[name], lw=1, label=labels[name])
        rss = np.asarray(rec["rss_mb"], dtype=np.float64).reshape(-1, 2)
        ax_rss.plot(rss[:, 0], rss[:, 1], color=colours[name], lw=1, label=labels[name])
        live = np.asarray(rec["live_landmarks"])
        ax_live.plot(np.arange(1, len(live) + 1), live, color=colours[name], lw=1)
        if len(rec["frame_ms"]) < n:
            for ax in axes:
                ax.axvline(len(rec["frame_ms"]), color=colours[name], ls=":", lw=1)
    for lo, hi in windows(n).values():
        for ax in axes:
            ax.axvspan(lo, hi, color="0.85", zorder=0)
    ax_ms.set_yscale("log")
    ax_ms.set_ylabel(f"ms / frame (rolling median, {ROLLING} frames)")
    ax_ms.legend(loc="upper left", fontsize=8)
    ax_ms.set_title(
        f"Lifelong run: {n} frames, {ROOMS[0]}x{ROOMS[1]} rooms, {LANDMARKS} landmarks, "
        f"seed {seed}\n(shaded: early and late windows; dotted: baseline stopped)",
        fontsize=10,
    )
    ax_rss.set_ylabel("process RSS (MiB)")
    ax_rss.legend(loc="upper left", fontsize=8)
    ax_live.set_ylabel("live landmarks")
    ax_live.set_xlabel("frame")
    ax_live.set_xlim(0, n)
    for ax in axes:
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def print_summary(report: dict[str, Any]) -> None:
    b = report["bounded"]
    f = report["bounded_figures"]
    c = report.get("comparison") or {}

    def fmt(x: Any, unit: str = "") -> str:
        return "n/a" if x is None else f"{x}{unit}"

    def goal(met: bool | None) -> str:
        return "" if met is None else ("  [goal met]" if met else "  [GOAL MISSED]")

    print()
    print(f"seed {report['seed']}  frames {report['frames']}  run digest {report['run_digest']}")
    print(
        f"{'bounded':10s} median ms early {f['early_window']}: {fmt(f['median_ms_early'])}"
        f"   late {f['late_window']}: {fmt(f['median_ms_late'])}"
        f"   ratio {fmt(f['time_ratio_late_over_early'])} (goal <= {TIME_RATIO_GOAL})"
        f"{goal(f['time_ratio_goal_met'])}"
    )
    print(
        f"{'':10s} speed probe early {fmt(f.get('speed_probe_ms_early'), ' ms')}"
        f"   late {fmt(f.get('speed_probe_ms_late'), ' ms')}"
        f"   ratio with the machine's speed taken out {fmt(f.get('time_ratio_speed_normalised'))}"
    )
    print(
        f"{'':10s} peak RSS at frame {f['rss_quarter_frame']}:"
        f" {fmt(f['peak_rss_at_quarter_mb'], ' MiB')}"
        f"   peak from then to the end: {fmt(f['peak_rss_end_mb'], ' MiB')}"
        f"   growth {fmt(f['peak_rss_growth_pct_end_vs_quarter'], ' %')}"
        f" (goal <= {RSS_GROWTH_GOAL_PCT} %, read on {f['rss_growth_goal_reading']})"
        f"{goal(f['rss_growth_goal_met'])}"
    )
    print(
        f"{'':10s} current RSS at frame {f['rss_quarter_frame']}:"
        f" {fmt(f['rss_at_quarter_mb'], ' MiB')}   growth to the later peak"
        f" {fmt(f['rss_growth_pct_peak_end_vs_quarter'], ' %')}, to the end's RSS"
        f" {fmt(f['rss_growth_pct_current_end_vs_quarter'], ' %')}"
    )
    print(
        f"{'':10s} steady RSS creep from frame {f['rss_quarter_frame']}:"
        f" {fmt(f.get('steady_rss_creep_bytes_per_frame'), ' B/frame')}"
        f"   trajectory rows held at most {f.get('held_trajectory_rows_max')},"
        f" keyframes at the end {(f.get('keyframes') or [[0, None]])[-1][1]},"
        f" spooled {f.get('spooled_trajectory_rows')}"
    )
    tail = f["tail"]
    print(
        f"{'':10s} tail per {tail['block_frames']} frames: worst p99/median"
        f" {fmt(tail['worst_p99_over_median'])} (goal <= {TAIL_P99_GOAL})"
        f"{goal(tail['p99_goal_met'])}, worst max/median"
        f" {fmt(tail['worst_max_over_median'])} (goal <= {TAIL_MAX_GOAL})"
        f"{goal(tail['max_goal_met'])}"
    )
    rest = f.get("tail_without_budget")
    if rest is not None:
        print(
            f"{'':10s} without the budget stage (removals, thinnings): worst p99/median"
            f" {fmt(rest['worst_p99_over_median'])}, worst max/median"
            f" {fmt(rest['worst_max_over_median'])}"
        )
    busy = f.get("tail_with_upkeep")
    if busy is not None:
        print(
            f"{'':10s} upkeep after the frame: median {fmt(f['upkeep_ms_median'], ' ms')}, p99"
            f" {fmt(f['upkeep_ms_p99'], ' ms')}, max {fmt(f['upkeep_ms_max'], ' ms')}; frame +"
            f" upkeep: worst p99/median {fmt(busy['worst_p99_over_median'])}, worst"
            f" max/median {fmt(busy['worst_max_over_median'])}"
        )
    live = b["live_landmarks"]
    print(
        f"{'':10s} live landmarks (from frame {live['from_frame']}): min {live['min']}"
        f" median {live['median']} max {live['max']}   removals {b['removals']}"
        f" (new {b.get('landmarks_added')}, restored {b.get('landmarks_restored')})"
        f"   ATE {fmt(b['accuracy']['ate_rmse_m'], ' m')}"
        f" (aligned {fmt(b['accuracy']['ate_rmse_aligned_m'], ' m')})"
        f"   wall {b['wall_s']} s"
    )
    base = report.get("baseline")
    print()
    print(f"{'window':>15s} {'bounded ms':>11s} {'baseline ms':>12s} {'ratio':>7s}")
    base_rows = {tuple(r["frames"]): r for r in (base or {}).get("checkpoints", [])}
    for row in b["checkpoints"]:
        key = tuple(row["frames"])
        other = base_rows.get(key)
        base_ms = f"{other['median_ms']:12.2f}" if other else f"{'':12s}"
        ratio = f"{other['median_ms'] / row['median_ms']:7.1f}" if other else ""
        print(f"{key[0]:>7d}-{key[1]:<7d} {row['median_ms']:11.2f} {base_ms} {ratio}")
    if base:
        print()
        print(
            f"baseline: {base['frames_done']} frames in {base['wall_s']} s"
            f" ({base['stop_reason']}), peak RSS {base['peak_rss_mb']} MiB,"
            f" ATE {fmt(base['accuracy']['ate_rmse_m'], ' m')}"
        )
        if "slowdown_baseline_over_bounded" in c:
            where = "end of run" if c["slowdown_is_at_end_of_run"] else "NOT the end of run"
            print(
                f"slowdown baseline/bounded at window {c['last_common_window']} ({where}):"
                f" {c['slowdown_baseline_over_bounded']}x (goal >= {BASELINE_SLOWDOWN_GOAL}x)"
                f"{goal(c['slowdown_goal_met_at_window'])}; CPU time {c['slowdown_cpu_time']}x"
                f"{goal(c['slowdown_goal_met_at_window_cpu_time'])}"
            )
        extra = c.get("EXTRAPOLATION_not_measured")
        if extra:
            print(
                f"  EXTRAPOLATED (not measured): ~{extra['baseline_median_ms_at_late_window']}"
                f" ms at the late window, ~{extra['slowdown_at_late_window']}x"
            )
    elif report.get("baseline_error"):
        print(f"baseline: {report['baseline_error']}")


# --------------------------------------------------------------------------- main
def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--frames", type=int, default=20_000)
    parser.add_argument(
        "--baseline-frames", type=int, default=None, help="frames for the baseline (default all)"
    )
    parser.add_argument("--baseline-budget-s", type=float, default=900.0)
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    parser.add_argument(
        "--records",
        type=Path,
        nargs="+",
        default=None,
        metavar="JSON",
        help="build the report from saved child records (bounded first, then the "
        "baseline) instead of running them: e.g. a long baseline run on its own with "
        "`--worker baseline --worker-out FILE`",
    )
    parser.add_argument(
        "--world", choices=sorted(WORLDS), default="standard", help="the simulated world's view"
    )
    parser.add_argument(
        "--blas-threads",
        type=int,
        default=1,
        help="numpy BLAS threads in the children (as the service's workers.blas_threads; 0 = "
        "the library's default)",
    )
    parser.add_argument(
        "--bounded-config",
        type=json.loads,
        default={},
        help="estimator settings of the bounded run changed, as JSON (SlamConfig fields, "
        "e.g. '{\"spare_observed\": true}')",
    )
    parser.add_argument("--name", default=None, help="results file stem (default by world)")
    parser.add_argument("--seed", type=int, default=SEED, help=argparse.SUPPRESS)
    parser.add_argument("--worker", choices=sorted(RUNS), default=None, help=argparse.SUPPRESS)
    parser.add_argument("--worker-max-frames", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--worker-budget-s", type=float, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--worker-out", type=Path, default=None, help=argparse.SUPPRESS)
    parser.add_argument(
        "--worker-heap-seed",
        type=int,
        default=None,
        help=argparse.SUPPRESS,  # see perturb_heap
    )
    parser.add_argument(
        "--worker-keep-heap",
        action="store_true",
        help=argparse.SUPPRESS,  # BearingSlam(release_heap=False), for comparison
    )
    args = parser.parse_args(argv)
    n = args.frames
    if n < 20:
        parser.error("--frames must be at least 20")

    if args.worker is not None:
        if args.worker_out is None:
            parser.error("--worker needs --worker-out")
        max_frames = n if args.worker_max_frames is None else min(n, args.worker_max_frames)
        seed = args.worker_heap_seed
        held = perturb_heap(seed) if seed is not None else []  # noqa: F841 (held for the run)
        run_worker(
            args.worker,
            n,
            args.seed,
            max_frames,
            args.worker_budget_s,
            args.worker_out,
            release_heap=not args.worker_keep_heap,
            world=args.world,
            blas_threads=args.blas_threads,
            settings=args.bounded_config if args.worker == "bounded" else None,
        )
        return

    started = time.perf_counter()
    print(f"seed {args.seed}: simulating {n} frames, {ROOMS} rooms, {LANDMARKS} landmarks")
    run = make_run(n, args.seed, args.world)
    digest = run_digest(run)
    gt = run.ground_truth
    del run
    print(f"run digest {digest}")

    base_frames = n if args.baseline_frames is None else min(n, args.baseline_frames)
    records: dict[str, dict[str, Any]] = {}
    if args.records is not None:
        for name, path in zip(("bounded", "baseline"), args.records, strict=False):
            records[name] = json.loads(path.read_text())
            if records[name].get("name") != name:
                parser.error(f"{path} holds a {records[name].get('name')!r} record, not {name}")
        if "baseline" in records:
            base_frames = records["baseline"]["frames_done"]
    else:
        records["bounded"] = spawn(
            "bounded", n, args.seed, n, None, args.world, args.blas_threads, args.bounded_config
        )
        if base_frames > 0:
            records["baseline"] = spawn(
                "baseline",
                n,
                args.seed,
                base_frames,
                args.baseline_budget_s or None,
                args.world,
                args.blas_threads,
            )

    bounded = records["bounded"]
    if bounded.get("crashed"):
        raise SystemExit(f"the bounded run's child process failed: {bounded}")
    for name, rec in records.items():
        if not rec.get("crashed") and rec["digest"] != digest:
            raise SystemExit(f"{name} child simulated a different run ({rec['digest']})")

    report: dict[str, Any] = {
        "benchmark": "lifelong: time per frame and RSS vs frame count, bounded vs plain iSAM2",
        "seed": args.seed,
        "frames": n,
        "world": {
            "rooms": list(ROOMS),
            "landmarks": LANDMARKS,
            "simulator": "indoor_sim",
            "view": args.world,
            "simulate_arguments": WORLDS[args.world],
        },
        "blas_threads": args.blas_threads,
        "bounded_config_changes": args.bounded_config,
        "run_digest": digest,
        "method": {
            "isolation": "each configuration in its own fresh child process (subprocess)"
            + (
                "; records read from " + ", ".join(p.name for p in args.records)
                if args.records
                else ""
            ),
            "timing": "perf_counter around BearingSlam.process(frame, with_covariance=False)",
            "rss": f"current RSS (/proc/self/statm) every {RSS_EVERY} frames; peak = "
            "ru_maxrss, reset at frame N/4 (/proc/self/clear_refs), so it is the peak from "
            "N/4 to N; the peak up to N/4 is peak_rss_before_reset_mb",
            "windows": "early [N/20, N/10), late [0.95N, N), checkpoints every N/20 frames",
            "baseline_limits": {
                "baseline_frames": base_frames,
                "baseline_budget_s": args.baseline_budget_s,
            },
        },
        "machine": machine_info(),
        "bounded_figures": bounded_figures(bounded, n),
        "bounded": run_summary(bounded, n, gt),
    }
    base = records.get("baseline")
    if base is not None and base.get("crashed"):
        report["baseline_error"] = f"child process failed (exit {base['returncode']})"
        report["comparison"] = {"baseline_truncated_at_frame": 0, "note": "baseline crashed"}
    elif base is not None:
        report["baseline"] = run_summary(base, n, gt)
        report["comparison"] = comparison(bounded, base, n, gt)
    report["total_wall_s"] = round(time.perf_counter() - started, 1)

    args.out.mkdir(parents=True, exist_ok=True)
    stem = "lifelong" if args.world == "standard" else f"lifelong_{args.world}"
    stem = args.name or stem
    json_path = args.out / f"{stem}.json"
    png_path = args.out / f"{stem}.png"
    json_path.write_text(json.dumps(report, indent=2) + "\n")
    plot(records, n, args.seed, png_path)
    print_summary(report)
    print(f"\nwrote {json_path} and {png_path} in {report['total_wall_s']} s")


if __name__ == "__main__":
    main()
