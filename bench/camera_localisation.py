"""Camera robots through the place localiser: start without a pose, and a kidnap.

A rendered two-room world (`indoor_sim` + `render`, 1024x256 panoramas). Robot r1
maps the first room with images, starting from its true pose: the staircase and
spin of bench.turns (70 frames). Then:

- **start**: robot r2 (a new robot, no ``initial_pose``) starts at a random pose
  within `--start-offset-m` of a pose on r1's path, any heading, and drives
  straight ahead in 5 cm steps; per start: the frames until its status is
  ``relocalised`` and the pose error at that frame (and 5 frames later). Two more
  robots start in the second room, which r1 never saw: they must not be relocalised;
- **kidnap**: r1 goes on from the end of its path, is carried to another pose of
  the room (a jump without odometry) and drives on; the frames until ``lost`` and
  until ``relocalised`` after the jump, and the pose error then.

Each run records the CPU time the localiser step adds to a tracked frame (the
filter on the frame's landmark matches) and to a frame of a robot searching (pose-free
matching and the filter), with the load average.

`--caps`: the whole bench once per landmark cap (``none``: uncapped). With a cap small
enough that most landmarks are archived before the new robots start, it measures
whether a robot recognises places whose landmarks were marginalised (the localiser
matches archived landmarks by their archived views). `--live-only` weighs live
landmarks only (the localiser before the archive of views; an ablation). Per start
also: success = relocalised with the pose within `--tolerance` (0.5 m, 15 deg) for
`--hold` (20) frames from then on; a wrong convergence = relocalised beyond it.

    python -m bench.camera_localisation [--seeds 0 1 2] [--starts 4] [--caps none 40]
        [--frames 30] [--out bench/results]
"""

from __future__ import annotations

import argparse
import datetime as dt
import itertools
import json
import math
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from graph.angles import wrap_angle
from graph.localiser import INITIALISING, LOST, RELOCALISED
from service.offline.datasets.camera_runs import (
    CAMERA,
    CONFIG,
    Leg,
    mapping_path,
    pose_error,
    render_leg,
    scene,
    start_pose,
    straight,
)
from service.offline.datasets.render import TexturedWorld
from service.pipeline import map_pipeline
from service.pipeline.localiser import landmark_map
from service.session import MapSession
from service.settings import StoreSettings
from service.store import MapRecord

TOLERANCE = (0.5, 15.0)
"""(m, deg) within which a relocalised pose counts as right."""
HOLD_FRAMES = 20


def new_session(tmp: Path, name: str, cap: int | None = None) -> MapSession:
    config = {**CONFIG, "landmark_cap": cap}
    record = MapRecord(name, name, "mapping", config, time.time())
    return MapSession.create(tmp / f"{name}.sqlite", record, StoreSettings(snapshot_every=10**6))


def post(session: MapSession, leg: Leg) -> list[dict[str, Any]]:
    """Post every frame; rows of (status, errors, localise CPU ms) per frame."""
    rows = []
    for (meta, image), truth in zip(leg.frames, leg.truth, strict=True):
        c0 = time.process_time()
        result = json.loads(session.submit(dict(meta), image).result_json)
        cpu_ms = 1e3 * (time.process_time() - c0)
        err_m, err_deg = pose_error(result["pose"], truth)
        rows.append(
            {
                "seq": meta["seq"],
                "status": result["localisation"]["status"],
                "error_m": err_m,
                "error_deg": err_deg,
                "observed": len(result["landmarks"]["observed"]),
                "localise_ms": result["timing_ms"]["localise"],
                "localise_cpu_ms": result["timing_ms"].get("localise_cpu", 0.0),
                "association_ms": result["timing_ms"].get("association", 0.0),
                "frame_cpu_ms": cpu_ms,
            }
        )
    return rows


def first(rows: list[dict[str, Any]], status: str, start: int = 0) -> int | None:
    """Index of the first row from `start` on with `status`."""
    return next((k for k in range(start, len(rows)) if rows[k]["status"] == status), None)


def within(row: dict[str, Any], tolerance: tuple[float, float]) -> bool:
    return row["error_m"] <= tolerance[0] and row["error_deg"] <= tolerance[1]


def held(rows: list[dict[str, Any]], tolerance: tuple[float, float], hold: int) -> dict[str, Any]:
    """Success (the first frame relocalised from which the pose stays within `tolerance`
    for `hold` frames, 1-based; None if none) and wrong convergences (frames relocalised
    beyond the tolerance)."""
    found = [k for k, row in enumerate(rows) if row["status"] == RELOCALISED]
    ok = next(
        (
            k
            for k in found
            if k + hold <= len(rows) and all(within(r, tolerance) for r in rows[k : k + hold])
        ),
        None,
    )
    return {
        "success_frame": None if ok is None else ok + 1,
        "wrong_convergences": sum(not within(rows[k], tolerance) for k in found),
        "relocalisations": len(found),
    }


def map_room(session: MapSession, world: TexturedWorld, seed: int) -> tuple[Leg, list[dict]]:
    path = mapping_path()
    leg = render_leg(
        world, path, robot="r1", rng=np.random.default_rng([seed, 1]), initial_pose=True
    )
    return leg, post(session, leg)


def run_starts(
    world: TexturedWorld,
    *,
    seed: int,
    starts: int,
    frames: int,
    offset_m: float,
    tmp: Path,
    cap: int | None = None,
    tolerance: tuple[float, float] = TOLERANCE,
    hold: int = HOLD_FRAMES,
) -> dict[str, Any]:
    """r1 maps; then `starts` new robots each start without a pose (one map)."""
    session = new_session(tmp, f"starts{seed}_{offset_m}_{cap}", cap)
    leg, mapping_rows = map_room(session, world, seed)
    live, archived = len(session.slam.landmarks), len(session.slam.archive)
    rng = np.random.default_rng([seed, 2])
    out = []
    for i in range(starts):
        start = start_pose(leg.truth, rng, offset_m)
        truth = straight(start, frames)
        r = render_leg(world, truth, robot=f"s{i}", rng=np.random.default_rng([seed, 3, i]))
        rows = post(session, r)
        k = first(rows, RELOCALISED)
        item: dict[str, Any] = {
            "start": start.tolist(),
            "relocalised_frame": None if k is None else k + 1,
            "statuses": [row["status"] for row in rows],
            **held(rows, tolerance, hold),
        }
        if k is not None:
            item["error_m"], item["error_deg"] = rows[k]["error_m"], rows[k]["error_deg"]
            later = min(k + 5, len(rows) - 1)
            item["error_m_5_later"] = rows[later]["error_m"]
            item["error_deg_5_later"] = rows[later]["error_deg"]
        search = [row for row in rows if row["status"] == INITIALISING]
        item["search_frame_cpu_ms_median"] = (
            float(np.median([row["frame_cpu_ms"] for row in search])) if search else None
        )
        item["search_localise_cpu_ms_median"] = (
            float(np.median([row["localise_cpu_ms"] for row in search])) if search else None
        )
        out.append(item)
    unmapped = []
    for i in range(2):  # in the second room, which r1 never saw: nothing to find
        start = np.array([rng.uniform(1.5, 4.5), rng.uniform(7.5, 10.5), rng.uniform(-3, 3)])
        r = render_leg(
            world, straight(start, frames), robot=f"u{i}", rng=np.random.default_rng([seed, 6, i])
        )
        rows = post(session, r)
        k = first(rows, RELOCALISED)
        unmapped.append(
            {
                "start": start.tolist(),
                "relocalised_frame": None if k is None else k + 1,
                "error_m": None if k is None else rows[k]["error_m"],
                "statuses": [row["status"] for row in rows],
            }
        )
    session.close()
    tracked = mapping_rows[10:]
    return {
        "seed": seed,
        "landmark_cap": cap,
        "live_landmarks_at_starts": live,
        "archived_landmarks_at_starts": archived,
        "start_offset_m": offset_m,
        "mapping_lost_frames": sum(r["status"] == LOST for r in mapping_rows),
        "mapping_localise_ms_median": float(np.median([r["localise_ms"] for r in tracked])),
        "mapping_localise_cpu_ms_median": float(np.median([r["localise_cpu_ms"] for r in tracked])),
        "mapping_localise_cpu_ms_p90": float(
            np.percentile([r["localise_cpu_ms"] for r in tracked], 90)
        ),
        "mapping_frame_cpu_ms_median": float(np.median([r["frame_cpu_ms"] for r in tracked])),
        "mapping_error_m_max": max(r["error_m"] for r in mapping_rows),
        "starts": out,
        "unmapped_starts": unmapped,
    }


def run_kidnap(
    world: TexturedWorld, *, seed: int, frames: int, tmp: Path, cap: int | None = None
) -> dict[str, Any]:
    """r1 maps, drives on 10 frames, is carried to another pose of its path, drives on."""
    session = new_session(tmp, f"kidnap{seed}_{cap}", cap)
    leg, _ = map_room(session, world, seed)
    archived = len(session.slam.archive)
    rng = np.random.default_rng([seed, 4])
    end = leg.truth[-1]
    before = straight(end, 10)
    target = leg.truth[rng.integers(5, len(leg.truth) // 2)].copy()
    target[2] = wrap_angle(target[2] + rng.uniform(-math.pi, math.pi))
    # Head towards the middle of the room within +-60 deg.
    target[2] = wrap_angle(
        math.atan2(3.0 - target[1], 3.0 - target[0]) + rng.uniform(-math.pi / 3, math.pi / 3)
    )
    after = straight(target, frames)
    truth = np.vstack([before, after])
    first_seq = len(leg.frames)
    r = render_leg(
        world,
        truth,
        robot="r1",
        rng=np.random.default_rng([seed, 5]),
        first_seq=first_seq,
        moved_before=True,
        jumps=frozenset({len(before)}),
    )
    # The first frame of this leg continues r1's chain: its odometry is the motion since
    # r1's last mapping frame (zero: it stands where the spin ended).
    rows = post(session, r)
    session.close()
    jump = len(before)
    lost = first(rows, LOST, jump)
    back = None if lost is None else first(rows, RELOCALISED, lost)
    out: dict[str, Any] = {
        "seed": seed,
        "landmark_cap": cap,
        "archived_landmarks_at_jump": archived,
        "jump_m": float(math.hypot(*(target[:2] - before[-1][:2]))),
        "jump_deg": math.degrees(abs(wrap_angle(target[2] - before[-1][2]))),
        "lost_before_jump": sum(row["status"] == LOST for row in rows[:jump]),
        "frames_to_lost": None if lost is None else lost - jump + 1,
        "frames_to_relocalised": None if back is None else back - jump + 1,
        "statuses": [row["status"] for row in rows],
        "error_m_end": rows[-1]["error_m"],
        "error_deg_end": rows[-1]["error_deg"],
    }
    if back is not None:
        out["error_m"], out["error_deg"] = rows[back]["error_m"], rows[back]["error_deg"]
        tail = rows[back:]
        out["error_m_after_median"] = float(np.median([row["error_m"] for row in tail]))
        out["error_m_after_max"] = max(row["error_m"] for row in tail)
    return out


def summary(doc: dict[str, Any]) -> dict[str, Any]:
    """One summary per landmark cap (key ``cap_none``, ``cap_40``, ...)."""
    caps = list(dict.fromkeys(run["landmark_cap"] for run in doc["start_runs"]))
    return {
        f"cap_{cap if cap is not None else 'none'}": cap_summary(
            [run for run in doc["start_runs"] if run["landmark_cap"] == cap],
            [run for run in doc["kidnap_runs"] if run["landmark_cap"] == cap],
        )
        for cap in caps
    }


def cap_summary(
    start_runs: list[dict[str, Any]], kidnap_runs: list[dict[str, Any]]
) -> dict[str, Any]:
    offsets = sorted({run["start_offset_m"] for run in start_runs})
    starts = [s for run in start_runs for s in run["starts"]]
    return {
        "live_landmarks_at_starts": [run["live_landmarks_at_starts"] for run in start_runs],
        "archived_landmarks_at_starts": [run["archived_landmarks_at_starts"] for run in start_runs],
        "all_starts": start_summary(starts),
        **{
            f"starts_within_{offset}m": start_summary(
                [s for run in start_runs if run["start_offset_m"] == offset for s in run["starts"]]
            )
            for offset in offsets
        },
        "unmapped_starts": sum(len(run["unmapped_starts"]) for run in start_runs),
        "unmapped_starts_relocalised_falsely": sum(
            s["relocalised_frame"] is not None for run in start_runs for s in run["unmapped_starts"]
        ),
        **kidnap_summary(start_runs, kidnap_runs),
    }


def start_summary(starts: list[dict[str, Any]]) -> dict[str, Any]:
    searching = [
        s["search_localise_cpu_ms_median"]
        for s in starts
        if s["search_localise_cpu_ms_median"] is not None
    ]
    found = [s for s in starts if s["relocalised_frame"] is not None]
    good = [s for s in found if s["error_m"] <= 0.3 and s["error_deg"] <= 10.0]
    success = [s["success_frame"] for s in starts if s["success_frame"] is not None]
    return {
        "starts": len(starts),
        "success_held": len(success),
        "success_percent": 100.0 * len(success) / len(starts) if starts else None,
        "success_frames_median": float(np.median(success)) if success else None,
        "success_frames_max": max(success, default=None),
        "wrong_convergences": sum(s["wrong_convergences"] for s in starts),
        "starts_with_wrong_convergence": sum(s["wrong_convergences"] > 0 for s in starts),
        "relocalised": len(found),
        "relocalised_within_0.3m_10deg": len(good),
        "frames_to_relocalise_median": float(np.median([s["relocalised_frame"] for s in found]))
        if found
        else None,
        "frames_to_relocalise_max": max((s["relocalised_frame"] for s in found), default=None),
        "error_m_median": float(np.median([s["error_m"] for s in found])) if found else None,
        "error_m_max": max((s["error_m"] for s in found), default=None),
        "error_deg_max": max((s["error_deg"] for s in found), default=None),
        "searching_frame_localise_cpu_ms_median": float(np.median(searching))
        if searching
        else None,
    }


def kidnap_summary(start_runs: list[dict[str, Any]], kid: list[dict[str, Any]]) -> dict[str, Any]:
    lost = [k["frames_to_lost"] for k in kid if k["frames_to_lost"] is not None]
    back = [k["frames_to_relocalised"] for k in kid if k["frames_to_relocalised"] is not None]
    return {
        "kidnaps": len(kid),
        "kidnaps_lost": sum(k["frames_to_lost"] is not None for k in kid),
        "kidnaps_relocalised": len(back),
        "kidnap_frames_to_lost": lost,
        "kidnap_frames_to_relocalised": back,
        "kidnap_lost_before_jump": sum(k["lost_before_jump"] for k in kid),
        "kidnap_error_m_end": [k["error_m_end"] for k in kid],
        "kidnap_error_m_after_max": max(
            (k["error_m_after_max"] for k in kid if "error_m_after_max" in k), default=None
        ),
        "tracked_frame_localise_cpu_ms_median": float(
            np.median([r["mapping_localise_cpu_ms_median"] for r in start_runs])
        ),
        "tracked_frame_localise_cpu_ms_p90_max": max(
            r["mapping_localise_cpu_ms_p90"] for r in start_runs
        ),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2])
    parser.add_argument("--starts", type=int, default=4, help="new robots per seed")
    parser.add_argument("--frames", type=int, default=30, help="frames per new robot")
    parser.add_argument(
        "--caps",
        nargs="*",
        default=["none", "40"],
        help="landmark caps, one bench each (none: uncapped)",
    )
    parser.add_argument(
        "--live-only",
        action="store_true",
        help="the filter weighs live landmarks only (ablation: no archived landmarks)",
    )
    parser.add_argument("--tolerance", type=float, nargs=2, default=list(TOLERANCE))
    parser.add_argument("--hold", type=int, default=HOLD_FRAMES)
    parser.add_argument(
        "--start-offset-m",
        type=float,
        nargs="*",
        default=[0.5, 1.0],
        help="starts lie within this distance of r1's path (one set of starts per value)",
    )
    parser.add_argument("--kidnap-frames", type=int, default=30)
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    args = parser.parse_args()
    doc: dict[str, Any] = {
        "when": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "load_average_start": [round(v, 2) for v in os.getloadavg()],
        "camera": f"panorama {CAMERA.width}x{CAMERA.height}",
        "args": {k: str(v) for k, v in vars(args).items()},
        "start_runs": [],
        "kidnap_runs": [],
    }
    if args.live_only:
        # The localiser as it was before archived landmarks: live ones only.
        map_pipeline.localisation_landmarks = landmark_map
    caps = [None if c == "none" else int(c) for c in args.caps]
    tolerance = (args.tolerance[0], args.tolerance[1])
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for seed, cap in itertools.product(args.seeds, caps):
            world = scene(seed)
            for offset in args.start_offset_m:
                run = run_starts(
                    world,
                    seed=seed,
                    starts=args.starts,
                    frames=args.frames,
                    offset_m=offset,
                    tmp=Path(tmp),
                    cap=cap,
                    tolerance=tolerance,
                    hold=args.hold,
                )
                doc["start_runs"].append(run)
                print(json.dumps({k: v for k, v in run.items() if k != "starts"}))
                for s in run["starts"]:
                    print(json.dumps({k: v for k, v in s.items() if k != "statuses"}))
            kid = run_kidnap(world, seed=seed, frames=args.kidnap_frames, tmp=Path(tmp), cap=cap)
            doc["kidnap_runs"].append(kid)
            print(json.dumps({k: v for k, v in kid.items() if k != "statuses"}))
    doc["seconds"] = time.perf_counter() - t0
    doc["load_average_end"] = [round(v, 2) for v in os.getloadavg()]
    doc["summary"] = summary(doc)
    print(json.dumps(doc["summary"], indent=1))
    args.out.mkdir(parents=True, exist_ok=True)
    name = "camera_localisation_live_only" if args.live_only else "camera_localisation"
    (args.out / f"{name}.json").write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
