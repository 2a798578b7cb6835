"""Do maps snapshotted by an older version load and go on as that version would?

Run from the repository root::

    python -m bench.older_snapshots [--before 7843223] [--out bench/results]

The older version's tree (``git archive <before>``) writes two maps with a snapshot:
a JSON map (300 simulated frames, then a second robot without ``initial_pose`` that
its particle filter finds) and a camera map (40 rendered panoramas, then a second
robot localised from its images). Then a copy of each is reopened and fed the rest of
its frames, once by the older tree and once by this one; a hash covers the frame
results (without timings), trajectories, poses, places, counts and (camera) the
exported front-end state, and the poses again after a reload from the new snapshot.
Equal hashes: this version reads the older snapshots and goes on bit for bit alike.

Writes ``<out>/older_snapshots.json``; prints it.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


def _lines(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _follower(docs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    out = []
    for doc in docs:
        follower = {**doc, "robot": "b"}
        follower.pop("initial_pose", None)
        out.append(follower)
    return out


def _streams(work: Path) -> dict[str, tuple[list[tuple[dict[str, Any], bytes | None]], int, dict]]:
    """Per map: (frames with their images, frames before the snapshot, map config)."""
    sim = _lines(work / "sim.jsonl")
    cam = _lines(work / "cam" / "frames.jsonl")
    json_frames = [*sim[:300], *_follower(sim[:40]), *sim[300:400], *_follower(sim)[40:80]]

    def image(doc: dict[str, Any]) -> tuple[dict[str, Any], bytes]:
        body = {k: v for k, v in doc.items() if k != "image"}
        return body, (work / "cam" / doc["image"]).read_bytes()

    cam_frames = [*cam[:40], *_follower(cam[:12]), *cam[40:50], *_follower(cam)[12:24]]
    camera = json.loads((work / "cam" / "camera.json").read_text())
    return {
        "json": ([(d, None) for d in json_frames], 340, {"seed": 0, "landmark_cap": 30}),
        "camera": ([image(d) for d in cam_frames], 52, {"seed": 0, "camera": camera}),
    }


def _phase(work: Path, phase: str, tag: str) -> dict[str, Any]:
    """Runs inside the tree under test (its `service` on the path)."""
    from service.session import MapSession
    from service.settings import StoreSettings
    from service.store import MapRecord

    try:  # this layout: queries as requests, export beside the session
        from service import queries
        from service.exchange import export_map

        def query(session: Any, op: str) -> Any:
            if hasattr(queries, "MapRequest"):
                return getattr(queries, op.title())().answer(session)
            return getattr(queries, op)(session)  # queries as functions

        def export(session: Any) -> Any:
            return export_map(session)
    except ImportError:  # the older layout: methods of the session

        def query(session: Any, op: str) -> Any:
            return getattr(session, op)()

        def export(session: Any) -> Any:
            return session.export()

    settings = StoreSettings(snapshot_every=10**6)
    out: dict[str, Any] = {}
    for name, (frames, split, config) in _streams(work).items():
        if phase == "create":
            record = MapRecord(name, name, "mapping", config, 0.0)
            session = MapSession.create(work / f"{name}.sqlite", record, settings)
            for body, image in frames[:split]:
                session.submit(body, image)
            session.snapshot()
            session.close()
            continue
        path = work / f"{name}_{tag}.sqlite"
        shutil.copy(work / f"{name}.sqlite", path)
        session = MapSession(path, settings)
        assert session.loaded_from_snapshot > 0, "the older snapshot was not used"
        results = []
        for body, image in frames[split:]:
            reply = session.submit(body, image)
            # this layout: a FrameReply; the older one: a dict
            text = reply["result_json"] if isinstance(reply, dict) else reply.result_json
            doc = json.loads(text)
            doc.pop("timing_ms")
            results.append(doc)
        session.snapshot()
        doc = {
            "results": results,
            **{op: query(session, op) for op in ("trajectory", "pose", "places")},
            "counts": query(session, "summary")["counts"],
            "frontend": export(session).get("frontend"),
        }
        session.close()
        session = MapSession(path, settings)
        doc["reloaded_pose"] = query(session, "pose")
        session.close()
        text = json.dumps(doc, sort_keys=True)
        out[name] = {"frames": len(results), "sha256": hashlib.sha256(text.encode()).hexdigest()}
    return out


def _run(tree: Path, work: Path, phase: str, tag: str) -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    code = (
        "import json, sys\n"
        f"sys.path.insert(0, {str(ROOT / 'bench')!r})\n"
        "from older_snapshots import _phase\n"
        f"print(json.dumps(_phase(__import__('pathlib').Path({str(work)!r}), {phase!r}, {tag!r})))"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=tree, env=env, check=True, capture_output=True, text=True
    )
    return dict(json.loads(done.stdout.strip().splitlines()[-1]))


def _covslam(*args: str) -> None:
    """This checkout's `covslam` command."""
    code = "import sys; from api.cli import main; sys.exit(main())"
    subprocess.run(
        [sys.executable, "-c", code, *args], cwd=ROOT, check=True, stdout=subprocess.DEVNULL
    )


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--before", default="7843223", help="git revision of the older tree")
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        old, work = tmp / "old", tmp / "work"
        old.mkdir()
        work.mkdir()
        archive = subprocess.run(
            ["git", "archive", args.before], cwd=ROOT, check=True, capture_output=True
        )
        subprocess.run(["tar", "-x", "-C", str(old)], input=archive.stdout, check=True)
        sim, cam = str(work / "sim.jsonl"), str(work / "cam")
        _covslam("simulate", sim, "--ground-truth", str(work / "gt.tum"), "--frames", "400")
        _covslam("render", cam, "--frames", "50", "--width", "1024")
        _run(old, work, "create", "")
        before = _run(old, work, "continue", "old")
        after = _run(ROOT, work, "continue", "new")
    doc = {
        "before": args.before,
        "older_tree": before,
        "this_tree": after,
        "equal": before == after,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "older_snapshots.json").write_text(json.dumps(doc, indent=2) + "\n")
    print(json.dumps(doc, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
