"""The `covslam` command line: replay frame files, MRCLAM, and the simulator."""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from frontend.cameras import PanoramaCamera, camera_from_config
from frontend.pipeline import FrontEnd
from graph.config import SlamConfig
from graph.policies import POLICY_NAMES
from graph.types import FrameInput
from service.offline.datasets.indoor_sim import make_world, simulate, write_run
from service.offline.datasets.mrclam import load_mrclam, mrclam_frames, mrclam_noise
from service.offline.datasets.render_run import write_rendered_run
from service.offline.evaluation import Trajectory, ate_rmse, dead_reckoning, read_tum, write_tum
from service.offline.replay import ImageFrame, read_replay_frames, replay
from service.pipeline.camera_config import CAMERA_LANDMARK_CAP, CAMERA_NOISE_DEFAULTS
from service.pipeline.config import (
    DEFAULT_LANDMARK_CAP,
    WINDOW_FIELDS,
    MapConfig,
    slam_config,
    window_settings,
)

log = logging.getLogger("covslam")
_DEFAULTS = SlamConfig()


def _optional_int(text: str) -> int | None:
    return None if text.lower() in ("none", "0", "off") else int(text)


def _optional_float(text: str) -> float | None:
    return None if text.lower() in ("none", "off") else float(text)


def _add_map_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--landmark-cap",
        type=_optional_int,
        default=argparse.SUPPRESS,
        help=(
            f"most live landmarks ('none' = uncapped; default {DEFAULT_LANDMARK_CAP}, on "
            f"camera maps {CAMERA_LANDMARK_CAP}, as the service creates them)"
        ),
    )
    p.add_argument(
        "--policy",
        choices=POLICY_NAMES,
        default="coverage",
        help="landmark-selection policy (default coverage)",
    )
    p.add_argument(
        "--pose-window",
        type=_optional_int,
        default=argparse.SUPPRESS,
        help=f"poses kept per robot before marginalisation (default {_DEFAULTS.pose_window}; "
        "'none'; given alone, the window does not grow)",
    )
    p.add_argument(
        "--window-observations",
        type=_optional_int,
        default=argparse.SUPPRESS,
        help="a window of sparse observations grows while its poses hold fewer bearing "
        f"factors than this (default {_DEFAULTS.window_observations}; 'none')",
    )
    p.add_argument(
        "--uncapped-window-observations",
        type=_optional_int,
        default=argparse.SUPPRESS,
        help="--window-observations of an uncapped map when that is not given "
        f"(default {_DEFAULTS.uncapped_window_observations}; 'none')",
    )
    p.add_argument(
        "--max-pose-window",
        type=int,
        default=argparse.SUPPRESS,
        help=f"most poses of a grown window (default {_DEFAULTS.max_pose_window})",
    )
    p.add_argument(
        "--huber",
        type=_optional_float,
        default=argparse.SUPPRESS,
        help=(
            f"Huber threshold in sigmas for bearings ('none': no robust loss; default "
            f"{_DEFAULTS.huber_k}, and on camera maps Geman-McClure at "
            f"{CAMERA_NOISE_DEFAULTS['huber_k']}, as the service creates them)"
        ),
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the policy's rng")
    p.add_argument("--trajectory", type=Path, help="write every frame's latest pose (TUM)")
    p.add_argument("--stats", type=Path, help="write per-frame figures (JSON)")
    p.add_argument(
        "--progress",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="progress bar (default: only on a terminal)",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="covslam", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true")
    sub = parser.add_subparsers(dest="command", required=True)

    rp = sub.add_parser(
        "replay",
        help="feed frames through the pipeline in-process",
        description="covslam replay FRAMES.jsonl | covslam replay mrclam DIR --robot N",
    )
    rp.add_argument("source", help="a frames file (JSON lines), or the word 'mrclam'")
    rp.add_argument("directory", nargs="?", type=Path, help="with 'mrclam': the dataset folder")
    rp.add_argument("--robot", type=int, default=1, help="with 'mrclam': robot 1-5")
    rp.add_argument("--ground-truth", type=Path, help="TUM ground truth: print ATE RMSE")
    rp.add_argument(
        "--url",
        help="post the frames to a running service (e.g. http://127.0.0.1:8000) instead of "
        "replaying in-process; retries on 503; then fetches the TUM trajectory",
    )
    rp.add_argument("--map-id", help="with --url: post into this existing map")
    rp.add_argument(
        "--camera",
        type=Path,
        help="camera config (JSON) for frames with an image (default: camera.json beside them)",
    )
    _add_map_options(rp)

    sv = sub.add_parser(
        "serve",
        help="run the HTTP service (REST API v1) with its store (SQLite or PostgreSQL)",
        description="Settings come from COVSLAM_* environment variables (nested with __); "
        "options given here override them.",
    )
    sv.add_argument("--host", help="bind address (default 127.0.0.1, COVSLAM_HOST)")
    sv.add_argument("--port", type=int, help="TCP port (default 8000, COVSLAM_PORT)")
    sv.add_argument("--data-dir", type=Path, help="store directory (default ./covslam-data)")
    sv.add_argument("--workers", type=int, help="worker processes (default: CPU count)")
    sv.add_argument(
        "--engine",
        choices=("local", "ray"),
        help="where maps run: local worker processes (default) or Ray actors (COVSLAM_ENGINE)",
    )
    sv.add_argument(
        "--ray-address",
        help="with --engine ray: 'auto', 'host:port' or 'local' (COVSLAM_RAY__ADDRESS)",
    )
    sv.add_argument(
        "--store-url",
        help="a directory (SQLite) or postgresql://... (COVSLAM_STORE__URL; default: --data-dir)",
    )

    rn = sub.add_parser(
        "render",
        help="render a run of the textured indoor world (frames.jsonl + PNGs + camera.json)",
    )
    rn.add_argument("out_dir", type=Path)
    rn.add_argument("--frames", type=int, default=200)
    rn.add_argument("--width", type=int, default=2048, help="panorama width (height = width/4)")
    rn.add_argument("--seed", type=int, default=0)

    sp = sub.add_parser("simulate", help="write a simulated indoor run as a frames file")
    sp.add_argument("frames_out", type=Path, help="frames file to write (JSON lines)")
    sp.add_argument("--ground-truth", type=Path, required=True, help="TUM file to write")
    sp.add_argument("--frames", type=int, default=2000)
    sp.add_argument("--landmarks", type=int, default=225)
    sp.add_argument("--rooms", default="3x3", help="room grid, e.g. 3x3")
    sp.add_argument("--seed", type=int, default=0)
    return parser


def _window_given(args: argparse.Namespace) -> dict[str, int | None]:
    """The window options given on the command line (the others take the map's defaults)."""
    return {k: getattr(args, k) for k in WINDOW_FIELDS if hasattr(args, k)}


def _config(args: argparse.Namespace) -> SlamConfig:
    extra = mrclam_noise() if args.source == "mrclam" else {}
    window = window_settings(_window_given(args))
    max_window = window["max_pose_window"]
    assert max_window is not None  # an int field
    return SlamConfig(
        landmark_cap=getattr(args, "landmark_cap", DEFAULT_LANDMARK_CAP),
        policy=args.policy,
        pose_window=window["pose_window"],
        window_observations=window["window_observations"],
        uncapped_window_observations=window["uncapped_window_observations"],
        max_pose_window=max_window,
        huber_k=getattr(args, "huber", _DEFAULTS.huber_k),
        **extra,
    )


def _map_config_doc(args: argparse.Namespace, camera: dict[str, Any] | None) -> dict[str, Any]:
    """The map config a replay asks for: cap and huber_k only if given, so that the
    service's defaults (a camera map's own) apply."""
    return {
        **({"landmark_cap": args.landmark_cap} if hasattr(args, "landmark_cap") else {}),
        "policy": args.policy,
        **_window_given(args),
        "noise": {
            **({"huber_k": args.huber} if hasattr(args, "huber") else {}),
            **(mrclam_noise() if args.source == "mrclam" else {}),
        },
        "seed": args.seed,
        "camera": camera,
    }


def camera_map_config(args: argparse.Namespace, camera: dict[str, Any]) -> SlamConfig:
    """The estimator of a camera map created from these options, as the service creates
    it (MapConfig.for_new_map with the service's default caps)."""
    doc = MapConfig.model_validate(_map_config_doc(args, camera))
    created = doc.for_new_map(DEFAULT_LANDMARK_CAP, CAMERA_LANDMARK_CAP)
    return slam_config(created.model_dump(mode="json"), "mapping")


def _replay(args: argparse.Namespace) -> int:
    gt: Trajectory | None
    front_end = None
    sequence: list[FrameInput | ImageFrame]
    if args.source == "mrclam":
        if args.directory is None:
            raise SystemExit("covslam replay mrclam: give the dataset folder")
        frames, gt = mrclam_frames(load_mrclam(args.directory, args.robot))
        sequence = list(frames)
        robot = f"r{args.robot}"
        log.info("MRCLAM robot %d: %d frames", args.robot, len(frames))
    else:
        sequence = read_replay_frames(args.source)
        frames = [it.frame if isinstance(it, ImageFrame) else it for it in sequence]
        gt = read_tum(args.ground_truth) if args.ground_truth else None
        robot = frames[0].robot if frames else ""
        if any(isinstance(it, ImageFrame) for it in sequence):
            camera_path = args.camera or Path(args.source).parent / "camera.json"
            camera = camera_from_config(json.loads(Path(camera_path).read_text()))
            front_end = FrontEnd(camera)
    if args.url:
        camera_config = None
        if front_end is not None:  # the service runs the front end: it needs the camera
            camera_config = front_end.camera.as_config()
            front_end.close()
        return _replay_http(args, sequence, frames, gt, robot, camera_config)
    if front_end is not None:
        config = camera_map_config(args, front_end.camera.as_config())
    else:
        config = _config(args)
    try:
        result = replay(
            sequence,
            config=config,
            seed=args.seed,
            total=len(sequence),
            progress=args.progress,
            front_end=front_end,
        )
    finally:
        if front_end is not None:
            front_end.close()
    traj = result.trajectory(robot) if frames else None
    if args.trajectory and traj is not None:
        write_tum(args.trajectory, traj)
    stats = result.stats()
    if gt is not None and traj is not None:
        stats["ate_rmse_m"] = ate_rmse(traj, gt)
        stats["dead_reckoning_ate_rmse_m"] = ate_rmse(dead_reckoning(frames), gt)
    if args.stats:
        args.stats.write_text(json.dumps(stats))
    summary = (
        f"{stats['frames']} frames, median {stats['median_frame_ms']:.2f} ms/frame, "
        f"{len(stats['removals'])} removals, peak RSS {stats['peak_rss_mb']:.0f} MiB"
    )
    if "ate_rmse_m" in stats:
        summary += (
            f", ATE RMSE {stats['ate_rmse_m']:.3f} m "
            f"(dead reckoning {stats['dead_reckoning_ate_rmse_m']:.3f} m)"
        )
    sys.stdout.write(summary + "\n")
    return 0


def _replay_http(
    args: argparse.Namespace,
    sequence: list[FrameInput | ImageFrame],
    frames: list[FrameInput],
    gt: Trajectory | None,
    robot: str,
    camera: dict[str, Any] | None,
) -> int:
    from service.offline.http_client import fetch_tum, replay_http

    config = _map_config_doc(args, camera)
    name = Path(str(args.directory or args.source)).name
    run = replay_http(
        sequence,
        url=args.url,
        map_id=args.map_id,
        name=name,
        config=config,
        progress=args.progress,
    )
    summary = run.summary()
    if frames:
        tum = fetch_tum(args.url, run.map_id, robot)
        if args.trajectory:
            args.trajectory.write_text(tum)
        if gt is not None:
            with tempfile.TemporaryDirectory() as tmp:
                path = Path(tmp) / "est.tum"
                path.write_text(tum)
                summary += f", ATE RMSE {ate_rmse(read_tum(path), gt):.3f} m"
    if args.stats:
        args.stats.write_text(json.dumps({"map_id": run.map_id, "latency_ms": run.latency_ms}))
    sys.stdout.write(summary + "\n")
    return 0


def _simulate(args: argparse.Namespace) -> int:
    rows, cols = (int(v) for v in args.rooms.lower().split("x"))
    rng = np.random.default_rng(args.seed)
    world = make_world(rooms=(rows, cols), landmarks=args.landmarks, rng=rng)
    run = simulate(world, frames=args.frames, rng=rng)
    write_run(run, args.frames_out, args.ground_truth)
    sys.stdout.write(f"wrote {len(run.frames)} frames to {args.frames_out}\n")
    return 0


def _settings_error(exc: ValidationError) -> str:
    """One line per wrong setting: `workers.count: Input should be ... (got 0)`."""
    return "; ".join(
        f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']} (got {e.get('input')!r})"
        for e in exc.errors()
    )


def _serve(args: argparse.Namespace) -> int:
    import uvicorn

    from api.app import create_app
    from service.settings import OpenBindError, Settings

    overrides: dict[str, object] = {}
    if args.host is not None:
        overrides["host"] = args.host
    if args.port is not None:
        overrides["port"] = args.port
    if args.data_dir is not None:
        overrides["data_dir"] = args.data_dir
    if args.engine is not None:
        overrides["engine"] = args.engine
    # nested options are validated like their COVSLAM_* variables (and merged with them)
    if args.workers is not None:
        overrides["workers"] = {"count": args.workers}
    if args.ray_address is not None:
        overrides["ray"] = {"address": args.ray_address}
    if args.store_url is not None:  # "" = SQLite in the data directory
        overrides["store"] = {"url": args.store_url}
    try:
        settings = Settings(**overrides)  # type: ignore[arg-type]
        settings.check_bind()
    except ValidationError as exc:
        sys.stderr.write(f"covslam serve: {_settings_error(exc)}\n")
        return 2
    except OpenBindError as exc:
        sys.stderr.write(f"covslam serve: {exc}\n")
        return 2
    if settings.engine == "ray":
        from service.ray_engine import RAY_MISSING, ray

        if ray is None:
            sys.stderr.write(f"covslam serve: {RAY_MISSING}\n")
            return 2
    logging.getLogger().setLevel(settings.log_level.upper())
    log.info(
        "serving on http://%s:%d (engine %s), store: %s",
        settings.host,
        settings.port,
        settings.engine,
        settings.store_location,
    )
    uvicorn.run(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        access_log=False,
        timeout_graceful_shutdown=5,
    )
    return 0


def _render(args: argparse.Namespace) -> int:
    camera = PanoramaCamera(args.width, args.width // 4)
    run = write_rendered_run(
        args.out_dir, frames=args.frames, rng=np.random.default_rng(args.seed), camera=camera
    )
    sys.stdout.write(f"wrote {run.frames} frames to {run.frames_path}\n")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    if args.command == "replay":
        return _replay(args)
    if args.command == "serve":
        return _serve(args)
    if args.command == "render":
        return _render(args)
    return _simulate(args)


if __name__ == "__main__":
    raise SystemExit(main())
