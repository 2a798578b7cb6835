"""A camera map's SQLite file with and without image pruning.

Run from the repository root (takes ~15 min for 800 frames on the 2-core machine)::

    python -m bench.image_store [--frames 800] [--out bench/results]

Renders a 2x2-room run of 2048x512 panoramas, feeds it through ``MapSession`` twice
(default store settings: a snapshot every 200 frames, two kept) -- once with
``prune_images`` on (the default), once off -- and every 100 frames records the
file's size (after a WAL checkpoint) and the number of stored images. At the end it
reports what each table holds. Writes ``<out>/image_store.json``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sqlite3
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from frontend.cameras import PanoramaCamera
from service.offline.datasets.render_run import write_rendered_run
from service.session import MapSession
from service.settings import StoreSettings
from service.store import MapRecord

log = logging.getLogger("bench.image_store")

CONFIG = {
    "landmark_cap": 200,
    "policy": "oldest",
    "camera": {"model": "panorama", "width": 2048, "height": 512},
}
TABLES = {
    "images": "data",
    "image_observations": "observations",
    "snapshots": "state",
    "frontend_states": "state",
    "frames": "length(body) + length(coalesce(result, ''))",
    "events": "data",
    "removals": "record",
}


def _tables(path: Path) -> dict[str, dict[str, float]]:
    """Rows and MiB of payload per table, and the file's free pages."""
    conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    out: dict[str, dict[str, float]] = {}
    for table, column in TABLES.items():
        size = column if "(" in column else f"length({column})"
        rows, total = conn.execute(
            f"SELECT count(*), coalesce(sum({size}), 0) FROM {table}"
        ).fetchone()
        out[table] = {"rows": rows, "mib": round(total / 2**20, 2)}
    page = conn.execute("PRAGMA page_size").fetchone()[0]
    free = conn.execute("PRAGMA freelist_count").fetchone()[0]
    out["free_pages"] = {"rows": free, "mib": round(free * page / 2**20, 2)}
    conn.close()
    return out


def _run(frames: list[tuple[dict[str, Any], bytes]], path: Path, prune: bool) -> dict[str, Any]:
    session = MapSession.create(
        path,
        MapRecord("cam", "bench", "mapping", CONFIG, time.time()),
        StoreSettings(prune_images=prune),
    )
    sizes = []
    for i, (meta, image) in enumerate(frames, 1):
        session.submit(meta, image)
        if session.snapshot_due:
            session.snapshot()
        if i % 100 == 0:
            session.store.checkpoint()
            sizes.append(
                {
                    "frame": i,
                    "file_mib": round(os.path.getsize(path) / 2**20, 1),
                    "images": session.store.image_count(),
                }
            )
            log.info("prune=%s %s", prune, sizes[-1])
    session.close()
    return {"prune_images": prune, "every_100_frames": sizes, "tables_at_end": _tables(path)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=800)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        rendered = write_rendered_run(
            work / "run",
            frames=args.frames,
            rng=np.random.default_rng(args.seed),
            camera=PanoramaCamera(2048, 512),
            rooms=(2, 2),
        )
        frames = []
        for line in rendered.frames_path.read_text().splitlines():
            doc = json.loads(line)
            frames.append((doc, (work / "run" / doc.pop("image")).read_bytes()))
        png_kib = float(np.mean([len(image) for _, image in frames])) / 1024
        runs = [_run(frames, work / f"map_{p}.sqlite", p) for p in (True, False)]
    report = {
        "benchmark": "image_store",
        "frames": args.frames,
        "mean_png_kib": round(png_kib, 1),
        "store": StoreSettings().model_dump(),
        "map_config": CONFIG,
        "loadavg": os.getloadavg(),
        "runs": runs,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "image_store.json").write_text(json.dumps(report, indent=1))
    for run in runs:
        end = run["every_100_frames"][-1]
        print(
            f"prune_images={run['prune_images']}: {end['file_mib']} MiB, {end['images']} images "
            f"after {end['frame']} frames; tables {run['tables_at_end']}"
        )


if __name__ == "__main__":
    main()
