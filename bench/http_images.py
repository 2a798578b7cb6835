"""Image frames end to end: rendered 2048x512 panoramas over HTTP vs in-process.

Run from the repository root (never during someone else's benchmark: 2 cores)::

    python -m bench.http_images [--frames 300] [--width 2048] [--render-dir DIR]
                                [--out bench/results]

A rendered run (service.offline.datasets.render_run, the 3x3 indoor world, PNG files) is
posted frame by frame. Every frame goes, in turn, through:

``pipeline``   ``ImageFrontEnd.submit(frame, png_bytes)`` in this process: decode,
               features, association, estimator (no log);
``session``    ``MapSession.submit(meta, png_bytes)`` in this process: the above plus
               the durable log (frame row + image blob, SQLite WAL) and the helper
               thread that extracts features while the frame is logged;
``http``       ``POST /v1/maps/{id}/frames`` multipart (meta + image) to a
               ``covslam serve`` on loopback, one client, keep-alive, waiting for
               each answer before the next frame (round trip as the client sees it).

The three are interleaved frame by frame so that they share whatever load the
machine carries. Then ``http_2_robots``: two clients at once post the same run
into one map as robots r1 and r2 (aggregate frames/s on one map), with the
worker's read-ahead on (the waiting frame's features are extracted while the
current one is associated and estimated) and, on a second server, off.

Reports frames/s (1000 / mean ms), p50/p99, the worker's per-stage milliseconds
(from the frame results), ``http_without_estimator`` (each HTTP round trip minus
the estimator's own time in the worker: what the image path costs around the
estimator), the load average, and writes
``<out>/http_images.json`` and ``<out>/http_images.png``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from frontend.cameras import PanoramaCamera
from frontend.pipeline import FrontEnd
from graph.slam import BearingSlam
from service.frames_io import frame_from_dict
from service.offline.datasets.render_run import write_rendered_run
from service.pipeline.camera_config import CAMERA_NOISE_DEFAULTS
from service.pipeline.config import MapConfig, slam_config
from service.pipeline.images import ImageFrontEnd
from service.session import MapSession
from service.settings import StoreSettings, WorkerSettings
from service.store import MapRecord

REPO = Path(__file__).resolve().parents[1]
STAGES = (
    "log",
    "decode",
    "features",
    "features_wait",
    "association",
    "update",
    "budget",
    "total",
)


def _rendered(directory: Path, frames: int, width: int) -> list[tuple[dict[str, Any], bytes]]:
    """(meta, PNG bytes) of a rendered run, rendered once into `directory`."""
    path = directory / "frames.jsonl"
    lines = path.read_text().splitlines() if path.exists() else []
    camera = json.loads((directory / "camera.json").read_text()) if lines else {}
    if len(lines) < frames or camera.get("width") != width:
        print(f"rendering {frames} frames of {width}x{width // 4} into {directory}")
        write_rendered_run(
            directory,
            frames=frames,
            rng=np.random.default_rng(0),
            camera=PanoramaCamera(width, width // 4),
        )
        lines = path.read_text().splitlines()
    out = []
    for line in lines[:frames]:
        doc = json.loads(line)
        out.append((doc, (directory / doc.pop("image")).read_bytes()))
    return out


def _serve(data_dir: Path, read_ahead: int | None = None) -> tuple[subprocess.Popen[bytes], str]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    env = {**os.environ, "COVSLAM_LOG_LEVEL": "warning"}
    if read_ahead is not None:
        env["COVSLAM_WORKERS__READ_AHEAD"] = str(read_ahead)
    proc = subprocess.Popen(
        [sys.executable, "-m", "api.cli", "serve", "--port", str(port),
         "--data-dir", str(data_dir), "--workers", "2"],
        cwd=REPO, env=env, start_new_session=True,
    )  # fmt: skip
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if httpx.get(url + "/readyz", timeout=1).status_code == 200:
                return proc, url
        except httpx.TransportError:
            pass
        time.sleep(0.1)
    raise TimeoutError("service did not become ready")


def _parts(meta: dict[str, Any], image: bytes, robot: str | None = None) -> dict[str, Any]:
    doc = meta if robot is None else {**meta, "robot": robot}
    return {
        "data": {"meta": json.dumps(doc, separators=(",", ":"))},
        "files": {"image": ("frame.png", image, "image/png")},
    }


def _tree_cpu_s(pid: int) -> float:
    """CPU seconds (user + system) of a process and all its descendants (Linux /proc)."""
    total = 0.0
    tick = os.sysconf("SC_CLK_TCK")
    pending = [pid]
    while pending:
        p = pending.pop()
        try:
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / tick
            for task in os.listdir(f"/proc/{p}/task"):
                kids = Path(f"/proc/{p}/task/{task}/children").read_text().split()
                pending.extend(int(k) for k in kids)
        except OSError:  # a process that ended meanwhile
            continue
    return total


def _post(client: httpx.Client, map_id: str, parts: dict[str, Any]) -> dict[str, Any]:
    r = client.post(f"/v1/maps/{map_id}/frames", **parts)
    if r.status_code != 200:
        raise RuntimeError(f"{r.status_code} {r.text[:300]}")
    result: dict[str, Any] = r.json()
    return result


def _stats(ms: list[float]) -> dict[str, float]:
    a = np.asarray(ms)
    return {
        "frames": len(a),
        "frames_per_s": 1e3 / float(a.mean()),
        "p50_ms": float(np.percentile(a, 50)),
        "p99_ms": float(np.percentile(a, 99)),
        "mean_ms": float(a.mean()),
    }


def _stage_medians(timings: list[dict[str, float]]) -> dict[str, float]:
    keys = sorted({k for t in timings for k in t})
    return {k: float(np.nanmedian([t.get(k, np.nan) for t in timings])) for k in keys}


def run(args: argparse.Namespace) -> dict[str, Any]:
    frames = _rendered(args.render_dir, args.frames, args.width)
    camera = PanoramaCamera(args.width, args.width // 4)
    config = {
        "landmark_cap": args.landmark_cap,
        "policy": args.policy,
        "pose_window": 100,
        "camera": camera.as_config(),
    }
    if args.optimizer is not None:
        config["optimizer"] = args.optimizer
    if args.graph_frame_distance is not None:
        config["graph_frame_distance_m"] = args.graph_frame_distance or None
    if args.bearing_loss is not None:  # with Huber's usual scale; GM with the camera's
        config["noise"] = (
            {"bearing_loss": "huber"} if args.bearing_loss == "huber" else CAMERA_NOISE_DEFAULTS
        )
    # The config as the service creates the map (camera defaults filled in), so that the
    # in-process runs and the HTTP map estimate alike.
    config = MapConfig.model_validate(config).for_new_map(None).model_dump(mode="json")
    load_start = os.getloadavg()
    print(f"{len(frames)} frames, load average {load_start[0]:.1f}, config {config}")
    pipeline = ImageFrontEnd(
        BearingSlam(slam_config(config, "mapping"), rng=np.random.default_rng(0)),
        FrontEnd(camera),
    )
    pipe_ms: list[float] = []
    pipe_stages: list[dict[str, float]] = []
    session_ms: list[float] = []
    session_stages: list[dict[str, float]] = []
    http_ms: list[float] = []
    http_stages: list[dict[str, float]] = []
    with tempfile.TemporaryDirectory() as tmp:
        record = MapRecord("bench", "bench", "mapping", config, time.time())
        session = MapSession.create(Path(tmp) / "bench.sqlite", record, StoreSettings())
        proc, url = _serve(Path(tmp) / "data")
        try:
            with httpx.Client(base_url=url, timeout=120) as client:
                r = client.post("/v1/maps", json={"name": "images", "config": config})
                assert r.status_code == 201, r.text
                map_id = r.json()["id"]
                server_cpu = [_tree_cpu_s(proc.pid)]
                for k, (meta, image) in enumerate(frames):
                    t0 = time.perf_counter()
                    res = pipeline.submit(frame_from_dict(meta), image)
                    t1 = time.perf_counter()
                    reply = session.submit(meta, image)
                    t2 = time.perf_counter()
                    result = _post(client, map_id, _parts(meta, image))
                    t3 = time.perf_counter()
                    pipe_ms.append(1e3 * (t1 - t0))
                    session_ms.append(1e3 * (t2 - t1))
                    http_ms.append(1e3 * (t3 - t2))
                    pipe_stages.append({**res.timing_ms, **res.outcome.timing_ms})
                    session_stages.append(reply.timing_ms)
                    http_stages.append(result["timing_ms"])
                    if (k + 1) % 50 == 0:
                        server_cpu.append(_tree_cpu_s(proc.pid))
                        print(
                            f"frame {k + 1}: pipeline {np.mean(pipe_ms[-50:]):.1f} ms, "
                            f"session {np.mean(session_ms[-50:]):.1f} ms, "
                            f"http {np.mean(http_ms[-50:]):.1f} ms"
                        )
                live = client.get(f"/v1/maps/{map_id}").json()["counts"]["live_landmarks"]
                two = _two_robots(url, config, frames[: args.two_robot_frames])
        finally:
            session.close()
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=30)
        proc, url = _serve(Path(tmp) / "data-no-read-ahead", read_ahead=0)
        try:
            two_off = _two_robots(url, config, frames[: args.two_robot_frames])
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=30)
    return {
        "frames": len(frames),
        "panorama": [camera.width, camera.height],
        "png_bytes_mean": float(np.mean([len(im) for _, im in frames])),
        "config": config,
        "sqlite_synchronous": StoreSettings().synchronous,
        "workers": 2,
        "worker_nice": WorkerSettings().nice,
        "cpus": os.cpu_count(),
        "load_average_at_start": load_start,
        "load_average_at_end": os.getloadavg(),
        "pipeline": {**_stats(pipe_ms), "stages_ms_median": _stage_medians(pipe_stages)},
        "session": {**_stats(session_ms), "stages_ms_median": _stage_medians(session_stages)},
        "http": {**_stats(http_ms), "stages_ms_median": _stage_medians(http_stages)},
        "http_2_robots": two,
        "http_2_robots_read_ahead_off": two_off,
        "read_ahead": WorkerSettings().read_ahead,
        "live_landmarks_end": live,
        "http_minus_session_ms_median": float(np.median(np.subtract(http_ms, session_ms))),
        "server_cpu_ms_per_frame_by_50": [
            1e3 * (b - a) / 50 for a, b in itertools.pairwise(server_cpu)
        ],
        "http_without_estimator": _stats(
            [h - st["total"] for h, st in zip(http_ms, http_stages, strict=True)]
        ),
        "goal_frames_per_s": 25.0,
        "ms": {"pipeline": pipe_ms, "session": session_ms, "http": http_ms},
    }


def _two_robots(
    url: str, config: dict[str, Any], frames: list[tuple[dict[str, Any], bytes]]
) -> dict[str, Any]:
    """Two clients post the run at once into one new map, as robots r1 and r2; frames/s,
    latency and the worker's median stage times (features_wait ~ 0: the features were
    extracted while the other robot's frame was processed)."""
    with httpx.Client(base_url=url, timeout=120) as client:
        r = client.post("/v1/maps", json={"name": "two", "config": config})
        assert r.status_code == 201, r.text
        map_id = r.json()["id"]
    lat: dict[str, list[float]] = {"r1": [], "r2": []}
    stages: list[dict[str, float]] = []

    def post_all(robot: str) -> None:
        with httpx.Client(base_url=url, timeout=120) as c:
            for meta, image in frames:
                t0 = time.perf_counter()
                result = _post(c, map_id, _parts(meta, image, robot))
                lat[robot].append(1e3 * (time.perf_counter() - t0))
                stages.append(result["timing_ms"])

    threads = [threading.Thread(target=post_all, args=(r,)) for r in lat]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    every = lat["r1"] + lat["r2"]
    return {
        "frames": len(every),
        "frames_per_s": len(every) / wall,
        "p50_ms": float(np.percentile(every, 50)),
        "p99_ms": float(np.percentile(every, 99)),
        "stages_ms_median": _stage_medians(stages),
    }


def plot(doc: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.5))
    names = ["pipeline", "session", "http", "http_2_robots", "http_2_robots_read_ahead_off"]
    fps = [doc[n]["frames_per_s"] for n in names]
    axes[0].bar(["pipeline\nin-process", "session\n+log", "HTTP\n1 client",
                 "HTTP\n2 robots", "2 robots\nno read-\nahead"], fps,
                color=["C0", "C1", "C2", "C3", "C4"])  # fmt: skip
    axes[0].tick_params(axis="x", labelsize=8)
    axes[0].axhline(doc["goal_frames_per_s"], color="k", ls="--", lw=1, label="goal 25/s")
    axes[0].set_ylabel("frames/s")
    axes[0].legend()
    load = doc["load_average_at_start"][0]
    axes[0].set_title(f"{doc['panorama'][0]}x{doc['panorama'][1]} PNG, load avg {load:.1f}")
    for name in ("pipeline", "session", "http"):
        a = np.sort(np.asarray(doc["ms"][name]))
        axes[1].plot(a, np.arange(1, len(a) + 1) / len(a), label=name)
    axes[1].set_xlabel("ms per frame")
    axes[1].set_ylabel("fraction of frames")
    axes[1].grid(alpha=0.3)
    axes[1].legend()
    stages = doc["http"]["stages_ms_median"]
    keys = [k for k in STAGES if k in stages]
    stage_labels = {"total": "estimator total"}
    axes[2].barh([stage_labels.get(k, k) for k in keys], [stages[k] for k in keys])
    axes[2].set_xlabel("median ms (worker, HTTP run)")
    axes[2].set_title("worker stages")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=100)
    p.add_argument(
        "--two-robot-frames", type=int, default=40, help="frames per robot, 2-robot runs"
    )
    p.add_argument("--width", type=int, default=2048)
    p.add_argument("--landmark-cap", type=int, default=200)
    p.add_argument("--policy", default="oldest")
    p.add_argument(
        "--optimizer",
        choices=["dogleg", "gauss_newton"],
        default=None,
        help="the map config's iSAM2 step (default: the service's, dogleg); results go to "
        "http_images_<optimizer>.json",
    )
    p.add_argument(
        "--graph-frame-distance",
        type=float,
        default=None,
        help="the map config's graph_frame_distance_m (default: the camera map's; 0: every "
        "frame in the graph)",
    )
    p.add_argument(
        "--bearing-loss",
        choices=["huber", "geman_mcclure"],
        default=None,
        help="the map config's bearing loss (default: the camera map's, geman_mcclure)",
    )
    p.add_argument(
        "--render-dir",
        type=Path,
        default=Path(tempfile.gettempdir()) / "covslam-bench-render",
        help="rendered run (made once, reused)",
    )
    p.add_argument("--name", help="results file name without suffix (default http_images)")
    p.add_argument("--out", type=Path, default=REPO / "bench" / "results")
    args = p.parse_args(argv)
    doc = run(args)
    args.out.mkdir(parents=True, exist_ok=True)
    name = args.name or (
        "http_images" if args.optimizer is None else f"http_images_{args.optimizer}"
    )
    (args.out / f"{name}.json").write_text(json.dumps(doc))
    plot(doc, args.out / f"{name}.png")
    for name in ("pipeline", "session", "http", "http_2_robots", "http_2_robots_read_ahead_off"):
        s = doc[name]
        print(f"{name:>28}: {s['frames_per_s']:.1f} frames/s, p50 {s['p50_ms']:.1f} ms, "
              f"p99 {s['p99_ms']:.1f} ms")  # fmt: skip
    print("stages (http, median ms):", json.dumps(doc["http"]["stages_ms_median"]))
    s = doc["http_without_estimator"]
    print(
        f"HTTP minus the estimator's time: {s['frames_per_s']:.1f} frames/s "
        f"(p50 {s['p50_ms']:.1f} ms); HTTP - session p50 "
        f"{doc['http_minus_session_ms_median']:.1f} ms"
    )
    cpu = ", ".join(f"{c:.1f}" for c in doc["server_cpu_ms_per_frame_by_50"])
    print(f"service CPU (API + workers) per frame, by 50 frames: {cpu} ms")
    print(f"load average start {doc['load_average_at_start']}, end {doc['load_average_at_end']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
