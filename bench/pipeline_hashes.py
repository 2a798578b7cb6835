"""Fingerprints of the frame pipeline: SHA-256 of final trajectories and frame results.

Run from the repository root::

    python -m bench.pipeline_hashes [--mrclam-frames 400] [--sim-frames 3000]
                                    [--camera-frames 60] [--out bench/results]

Three runs, each through the offline replay (the ``covslam replay`` command) and
through a map session in process (a temporary SQLite store; the localiser, the
snapshots and a reload half way included):

``mrclam``
    MRCLAM-6 robot 1: the whole run replayed, its first ``--mrclam-frames`` frames
    through the session (skipped without the data).
``sim``
    a lifelong simulated indoor run of ``--sim-frames`` frames (3x3 rooms, seed 0);
    in the session a second robot follows without ``initial_pose`` (the localiser's
    off-graph path).
``camera``
    a rendered panorama run of ``--camera-frames`` frames (1024 x 256); in the session a
    second robot without ``initial_pose`` is localised from its images.

A hash covers the final trajectory (every frame's latest pose, as text of the floats'
``repr``) and, for a session, each frame result without its timings. Two code
versions that give the same hashes process these frames bit for bit alike.

Writes ``<out>/pipeline_hashes.json``; prints it.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from service import queries
from service.frames_io import frame_to_dict
from service.offline.datasets.mrclam import load_mrclam, mrclam_frames, mrclam_noise
from service.session import MapSession
from service.settings import StoreSettings
from service.store import MapRecord


def _sha(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


ROOT = Path(__file__).resolve().parents[1]
DATA_DIR = Path(os.environ.get("COVSLAM_DATA", ROOT.parent / "shared" / "data"))
_MAIN = (
    "import sys\n"
    "try:\n    from api.cli import main\n"
    "except ImportError:\n    from api.cli import main\n"
    "sys.argv[0] = 'covslam'\nsys.exit(main())"
)


def _covslam(*args: str) -> None:
    """The `covslam` command of this checkout (run from its root, whatever is installed)."""
    subprocess.run(
        [sys.executable, "-c", _MAIN, *args], check=True, stdout=subprocess.DEVNULL, cwd=ROOT
    )


def _tum_hash(path: Path) -> str:
    return _sha(path.read_text())


def _session_run(
    where: Path,
    config: dict[str, Any],
    frames: Iterable[tuple[dict[str, Any], bytes | None]],
    *,
    reload_at: int,
) -> dict[str, str]:
    """Frames through a map session (reopened after `reload_at` frames); hashes of the
    results (timings left out) and the final trajectories."""
    record = MapRecord("hash", "hash", "mapping", config, 0.0)
    settings = StoreSettings(snapshot_every=100)
    session = MapSession.create(where, record, settings)
    results = []
    for k, (body, image) in enumerate(frames):
        if k == reload_at:
            session.snapshot()
            session.close()
            session = MapSession(where, settings)
        reply = session.submit(body, image)
        doc = json.loads(reply.result_json)
        doc.pop("timing_ms")
        results.append(doc)
        if session.snapshot_due:
            session.snapshot()
    trajectory = queries.Trajectory().answer(session)
    session.close()
    return {
        "results": _sha(json.dumps(results, sort_keys=True)),
        "trajectory": _sha(json.dumps(trajectory, sort_keys=True)),
        "frames": str(len(results)),
    }


def _lines(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _follower(docs: list[dict[str, Any]], n: int) -> list[dict[str, Any]]:
    """The first `n` frames again as a robot "b" that starts without initial_pose."""
    out = []
    for doc in docs[:n]:
        follower = {**doc, "robot": "b"}
        follower.pop("initial_pose", None)
        out.append(follower)
    return out


def mrclam(tmp: Path, frames: int, directory: Path) -> dict[str, Any]:
    if not directory.is_dir():
        return {"skipped": f"no MRCLAM-6 data at {directory}"}
    all_frames, _ = mrclam_frames(load_mrclam(directory, 1))
    docs = [frame_to_dict(f) for f in all_frames[:frames]]
    out = tmp / "mrclam.tum"
    _covslam("replay", "mrclam", str(directory), "--robot", "1", "--trajectory", str(out))
    config = {"noise": mrclam_noise(), "seed": 0}
    session = _session_run(
        tmp / "mrclam.sqlite", config, ((d, None) for d in docs), reload_at=frames // 2
    )
    return {"frames": len(all_frames), "replay": _tum_hash(out), "session": session}


def sim(tmp: Path, frames: int, _: Path) -> dict[str, Any]:
    path, gt = tmp / "sim.jsonl", tmp / "sim_gt.tum"
    _covslam("simulate", str(path), "--ground-truth", str(gt), "--frames", str(frames))
    out = tmp / "sim.tum"
    _covslam("replay", str(path), "--trajectory", str(out), "--landmark-cap", "50")
    docs = _lines(path)
    stream = [*docs, *_follower(docs, 60)]
    session = _session_run(
        tmp / "sim.sqlite",
        {"landmark_cap": 50, "seed": 0},
        ((d, None) for d in stream),
        reload_at=len(docs) // 2,
    )
    return {"frames": len(docs), "replay": _tum_hash(out), "session": session}


def camera(tmp: Path, frames: int, _: Path) -> dict[str, Any]:
    run = tmp / "rendered"
    _covslam("render", str(run), "--frames", str(frames), "--width", "1024")
    out = tmp / "camera.tum"
    _covslam("replay", str(run / "frames.jsonl"), "--trajectory", str(out))
    docs = _lines(run / "frames.jsonl")
    images = {d["seq"]: (run / d["image"]).read_bytes() for d in docs}
    stream = [*docs, *_follower(docs, 20)]
    camera_doc = json.loads((run / "camera.json").read_text())

    def bodies() -> Iterable[tuple[dict[str, Any], bytes | None]]:
        for d in stream:
            yield {k: v for k, v in d.items() if k != "image"}, images[d["seq"]]

    session = _session_run(
        tmp / "camera.sqlite", {"camera": camera_doc, "seed": 0}, bodies(), reload_at=frames // 2
    )
    return {"frames": len(docs), "replay": _tum_hash(out), "session": session}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--mrclam-frames", type=int, default=400)
    parser.add_argument("--sim-frames", type=int, default=3000)
    parser.add_argument("--camera-frames", type=int, default=60)
    parser.add_argument("--mrclam-dir", type=Path, default=DATA_DIR / "mrclam6")
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    args = parser.parse_args(argv)
    doc: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        for name, run, n in (
            ("mrclam", mrclam, args.mrclam_frames),
            ("sim", sim, args.sim_frames),
            ("camera", camera, args.camera_frames),
        ):
            t0 = time.perf_counter()
            doc[name] = run(tmp, n, args.mrclam_dir)
            doc[name]["seconds"] = round(time.perf_counter() - t0, 1)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "pipeline_hashes.json").write_text(json.dumps(doc, indent=2) + "\n")
    print(json.dumps(doc, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
