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
service now steps its own filter on image frames too (service.camera_localisation), on
the landmark matches only, so the two can differ); the position and heading error of the
reported pose; the landmarks the frame observed.

    python -m bench.turns [--turn-frames 1] [--out bench/results]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from frontend.cameras import PanoramaCamera
from graph.angles import wrap_angle
from graph.localiser import LOST, Localiser
from graph.types import FrameInput, Odometry, Pose2D
from service.datasets.indoor_sim import make_world
from service.datasets.mrclam import relative_motion
from service.datasets.render import make_textured_world, render_panorama
from service.frames_io import frame_to_dict
from service.localisation import MapLocalisation, map_localiser_config, to_map_frame
from service.session import MapSession
from service.settings import StoreSettings
from service.store import MapRecord

FloatArray = NDArray[np.float64]
CAMERA = PanoramaCamera(1024, 256)
CONFIG = {
    "landmark_cap": None,
    "pose_window": 30,
    "camera": {"model": "panorama", "width": CAMERA.width, "height": CAMERA.height},
}


def turn_path(
    *,
    start_xytheta: tuple[float, float, float] = (1.5, 1.5, 0.0),
    legs: int = 6,
    leg_m: float = 1.0,
    step_m: float = 0.1,
    turn_frames: int = 1,
    spin_turns: int = 4,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """True poses ``(F, 3)`` of the staircase and the closing spin, and ``(F,)`` True for
    the frames that end a turn step.

    Legs alternate heading +x / +y (left turn, right turn, ...); after the last leg the
    robot turns left `spin_turns` times by 90 degrees on the spot. A 90-degree turn takes
    `turn_frames` frames."""
    x, y, theta = start_xytheta
    poses = [(x, y, theta)]
    turning = [False]

    def turn(sign: float) -> None:
        nonlocal theta
        for _ in range(turn_frames):
            theta = wrap_angle(theta + sign * (math.pi / 2) / turn_frames)
            poses.append((x, y, theta))
            turning.append(True)

    for leg in range(legs):
        for _ in range(round(leg_m / step_m)):
            x += step_m * math.cos(theta)
            y += step_m * math.sin(theta)
            poses.append((x, y, theta))
            turning.append(False)
        turn(1.0 if leg % 2 == 0 else -1.0)
    for _ in range(spin_turns - 1):
        turn(1.0)
    return np.array(poses), np.array(turning)


@dataclass(frozen=True)
class TurnRun:
    frames: list[FrameInput]
    images: list[bytes]
    truth: FloatArray
    turning: NDArray[np.bool_]


def render_turn_run(
    *,
    rng: np.random.Generator,
    turn_frames: int = 1,
    legs: int = 6,
    spin_turns: int = 4,
    odometry_noise: tuple[float, float, float] = (0.02, 0.02, 0.02),
) -> TurnRun:
    """The frames (first with the true initial pose; odometry = true motion + noise with
    sigmas ``(kx d, ky d, kt (d + |dtheta|))``), their PNG panoramas, the truth."""
    world = make_world(rooms=(1, 2), landmarks=2, rng=rng)
    textured = make_textured_world(world, rng=rng)
    truth, turning = turn_path(legs=legs, turn_frames=turn_frames, spin_turns=spin_turns)
    motion = relative_motion(truth)
    kx, ky, kt = odometry_noise
    frames, images = [], []
    for k, pose in enumerate(truth):
        image, _ = render_panorama(textured, pose, CAMERA)
        ok, png = cv2.imencode(".png", image)
        if not ok:
            raise RuntimeError("could not encode a panorama")
        images.append(png.tobytes())
        if k == 0:
            frames.append(FrameInput("r1", 0, 0.0, initial_pose=Pose2D(*(float(v) for v in pose))))
            continue
        d = float(np.hypot(*motion[k - 1, :2]))
        sig = np.array([kx * d, ky * d, kt * (d + abs(motion[k - 1, 2]))])
        dx, dy, dth = motion[k - 1] + rng.normal(0.0, 1.0, 3) * sig
        frames.append(
            FrameInput("r1", k, 0.1 * k, odometry=Odometry(float(dx), float(dy), float(dth)))
        )
    return TurnRun(frames, images, truth, turning)


def run_turns(run: TurnRun, *, seed: int = 0, compass: bool = True) -> dict[str, Any]:
    """Every frame through a MapSession with a camera map, and a watch filter beside it.
    `compass` False: the front end predicts from the odometry alone (service.vision)."""
    watch = Localiser(map_localiser_config())
    watch_rng = np.random.default_rng([seed, 5])
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        record = MapRecord("turns", "turns", "mapping", CONFIG, time.time())
        session = MapSession.create(
            Path(tmp) / "turns.sqlite", record, StoreSettings(snapshot_every=10**6)
        )
        assert session.vision is not None
        session.vision.pipeline.compass = compass
        for k, (frame, image) in enumerate(zip(run.frames, run.images, strict=True)):
            meta = frame_to_dict(frame)
            del meta["observations"]
            result = json.loads(session.submit(meta, image)["result_json"])
            obs = session.store.image_observations(result["frame_id"]) or []
            pose = result["pose"]
            cov = np.asarray(result["covariance"], dtype=np.float64)
            odo = frame.odometry
            step = watch.step(
                frame.robot,
                odometry=None if odo is None else (odo.dx, odo.dy, odo.dtheta),
                dt_s=0.0 if k == 0 else frame.stamp - run.frames[k - 1].stamp,
                labels=[o["label"] for o in obs],
                bearings_rad=[o["bearing"] for o in obs],
                sigmas_rad=[o.get("sigma") for o in obs],
                landmarks=MapLocalisation.landmark_map(session.slam),
                graph_pose=(
                    np.array([pose["x"], pose["y"], pose["theta"]]),
                    to_map_frame(cov, pose["theta"]),
                ),
                rng=watch_rng,
            )
            truth = run.truth[k]
            rows.append(
                {
                    "seq": frame.seq,
                    "turning": bool(run.turning[k]),
                    "status": result["localisation"]["status"],
                    "watch_status": step.status,
                    "error_m": float(math.hypot(pose["x"] - truth[0], pose["y"] - truth[1])),
                    "error_deg": math.degrees(abs(wrap_angle(pose["theta"] - truth[2]))),
                    "watch_error_m": float(np.hypot(*(step.estimate.pose_xytheta[:2] - truth[:2]))),
                    "observed": len(result["landmarks"]["observed"]),
                    "added": len(result["landmarks"]["added"]),
                    "live": result["landmarks"]["live"],
                }
            )
        session.close()
    return summarise(rows)


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    turns = [r for r in rows if r["turning"]]
    after = [rows[k + 1] for k, r in enumerate(rows[:-1]) if r["turning"]]

    def stats(sel: list[dict[str, Any]], key: str) -> dict[str, float]:
        v = np.array([r[key] for r in sel], dtype=np.float64)
        return {"median": float(np.median(v)), "max": float(np.max(v))} if len(v) else {}

    return {
        "frames": len(rows),
        "turn_frames": len(turns),
        "statuses": sorted({r["status"] for r in rows}),
        "watch_statuses": sorted({r["watch_status"] for r in rows}),
        "lost_frames": sum(r["status"] == LOST for r in rows),
        "watch_lost_frames": sum(r["watch_status"] == LOST for r in rows),
        "error_m": stats(rows, "error_m"),
        "error_m_turn_frames": stats(turns, "error_m"),
        "error_deg": stats(rows, "error_deg"),
        "error_deg_turn_frames": stats(turns, "error_deg"),
        "observed_straight_frames": stats([r for r in rows if not r["turning"]], "observed"),
        "observed_turn_frames": stats(turns, "observed"),
        "observed_after_turn": stats(after, "observed"),
        "added_straight_frames": stats([r for r in rows if not r["turning"]], "added"),
        "added_turn_frames": stats(turns, "added"),
        "watch_error_m": stats(rows, "watch_error_m"),
        "rows": rows,
    }


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
