"""Rendered camera runs: a robot driving through a textured `indoor_sim` world, each
frame a 1024x256 panorama with noisy odometry; and a run of on-the-spot turns through a
camera map (MapSession) with a watch filter beside it.

Used by the camera benchmarks (turns, camera localisation) and their tests; never by the
service at run time.

Convention: poses are ``(F, 3)`` arrays of (x [m], y [m], theta [rad]) in the world
frame; odometry sigmas are ``(kx, ky per metre, kt per (metre + radian))``.
"""

from __future__ import annotations

import json
import math
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
from service.frames_io import frame_to_dict
from service.offline.datasets.indoor_sim import make_world
from service.offline.datasets.mrclam import relative_motion
from service.offline.datasets.render import TexturedWorld, make_textured_world, render_panorama
from service.pipeline.covariance import to_map_frame
from service.pipeline.localiser import landmark_map, map_localiser_config
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

ODOMETRY_NOISE = (0.02, 0.02, 0.02)
"""Odometry sigmas (kx, ky per metre, kt per (metre + radian))."""
STEP_M = 0.05
"""A searching robot's step per frame."""


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
    `compass` False: the front end predicts from the odometry alone (service.pipeline.images)."""
    watch = Localiser(map_localiser_config())
    watch_rng = np.random.default_rng([seed, 5])
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        record = MapRecord("turns", "turns", "mapping", CONFIG, time.time())
        session = MapSession.create(
            Path(tmp) / "turns.sqlite", record, StoreSettings(snapshot_every=10**6)
        )
        assert session.pipeline.images is not None
        session.pipeline.images.compass = compass
        for k, (frame, image) in enumerate(zip(run.frames, run.images, strict=True)):
            meta = frame_to_dict(frame)
            del meta["observations"]
            result = json.loads(session.submit(meta, image).result_json)
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
                landmarks=landmark_map(session.slam),
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


@dataclass(frozen=True)
class Leg:
    """Frames of one robot: (meta, PNG bytes) each, and the true poses (F, 3)."""

    frames: list[tuple[dict[str, Any], bytes]]
    truth: FloatArray


def scene(seed: int) -> TexturedWorld:
    rng = np.random.default_rng(seed)
    return make_textured_world(make_world(rooms=(1, 2), landmarks=2, rng=rng), rng=rng)


def render_leg(
    world: TexturedWorld,
    truth: FloatArray,
    *,
    robot: str,
    rng: np.random.Generator,
    first_seq: int = 0,
    initial_pose: bool = False,
    moved_before: bool = False,
    jumps: frozenset[int] = frozenset(),
) -> Leg:
    """Frames along `truth` ``(F, 3)``: odometry = true motion + noise (none across a
    frame in `jumps`: the robot was carried there); the first frame has odometry only if
    `moved_before` (zero motion), and the true pose as initial_pose if `initial_pose`."""
    motion = relative_motion(truth)
    kx, ky, kt = ODOMETRY_NOISE
    frames = []
    for k, pose in enumerate(truth):
        image, _ = render_panorama(world, pose, CAMERA)
        ok, png = cv2.imencode(".png", image)
        if not ok:
            raise RuntimeError("could not encode a panorama")
        seq = first_seq + k
        meta: dict[str, Any] = {"robot": robot, "seq": seq, "stamp": 0.1 * seq}
        if k == 0:
            if initial_pose:
                meta["initial_pose"] = {"x": pose[0], "y": pose[1], "theta": pose[2]}
            if moved_before:
                meta["odometry"] = {"dx": 0.0, "dy": 0.0, "dtheta": 0.0}
        else:
            m = motion[k - 1]
            if k in jumps:
                m = np.zeros(3)
            d = float(np.hypot(m[0], m[1]))
            sig = np.array([kx * d, ky * d, kt * (d + abs(m[2]))])
            dx, dy, dth = m + rng.normal(0.0, 1.0, 3) * sig
            meta["odometry"] = {"dx": float(dx), "dy": float(dy), "dtheta": float(dth)}
        frames.append((meta, png.tobytes()))
    return Leg(frames, np.asarray(truth, dtype=np.float64))


def straight(start: FloatArray, frames: int, step_m: float = STEP_M) -> FloatArray:
    """``(frames, 3)`` poses driving straight ahead from `start`."""
    k = np.arange(frames)[:, None]
    heading = np.array([math.cos(start[2]), math.sin(start[2]), 0.0])
    return np.asarray(start, dtype=np.float64)[None, :] + k * step_m * heading[None, :]


def mapping_path() -> FloatArray:
    poses, _ = turn_path(legs=6, turn_frames=1, spin_turns=4)
    return poses


def start_pose(path: FloatArray, rng: np.random.Generator, offset_m: float) -> FloatArray:
    """A pose within `offset_m` of a random pose of `path`, heading towards the room's
    middle (3, 3) within +-60 degrees (room to drive straight ahead)."""
    p = path[rng.integers(len(path))]
    r, a = offset_m * math.sqrt(rng.random()), rng.uniform(-math.pi, math.pi)
    x, y = p[0] + r * math.cos(a), p[1] + r * math.sin(a)
    heading = math.atan2(3.0 - y, 3.0 - x) + rng.uniform(-math.pi / 3, math.pi / 3)
    return np.array([x, y, wrap_angle(heading)])


def pose_error(pose: dict[str, float], truth: FloatArray) -> tuple[float, float]:
    """(position error m, heading error deg) of a result pose against the truth."""
    return (
        float(math.hypot(pose["x"] - truth[0], pose["y"] - truth[1])),
        math.degrees(abs(wrap_angle(pose["theta"] - truth[2]))),
    )
