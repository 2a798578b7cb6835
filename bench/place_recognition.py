"""Appearance-based place recognition on rendered panoramas (frontend.appearance).

A textured 3x3-room world (service.offline.datasets.render); places at random poses inside the
rooms (away from the walls), each with the signature of the panorama rendered there at
yaw 0. Queries near each place: any yaw (uniform over 0-360 deg), a position offset
(`--offsets`, metres, random direction), and a lighting change (gain 0.5-1.5, gamma
0.6-1.6, offset +-20 grey levels, pixel noise sigma 3). Top-1: the place nearest to
the query's position scores best among all places (also given: the place the query
was drawn around, which a query far from it may not be nearest to). Also the yaw
error of the matched offset, and the milliseconds of a signature and of a match
against all places (and against 100).

    python -m bench.place_recognition [--places 36] [--queries 10] [--out bench/results]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from frontend.appearance import AppearanceIndex, SignatureConfig, signature
from frontend.cameras import PanoramaCamera
from graph.angles import wrap_angle
from service.offline.datasets.indoor_sim import make_world
from service.offline.datasets.render import make_textured_world, render_panorama


def relight(image: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, dict[str, float]]:
    """A random global lighting change and sensor noise."""
    gain, gamma = rng.uniform(0.5, 1.5), rng.uniform(0.6, 1.6)
    offset = rng.uniform(-20.0, 20.0)
    x = 255.0 * gain * (image.astype(np.float64) / 255.0) ** gamma + offset
    x += rng.normal(0.0, 3.0, x.shape)
    return np.clip(np.rint(x), 0, 255).astype(np.uint8), {
        "gain": gain,
        "gamma": gamma,
        "offset": offset,
    }


def place_poses(n: int, rooms: tuple[int, int], size_m: float, rng: np.random.Generator):
    """(n, 2) positions spread over the rooms, at least 1.2 m from every wall."""
    room = rng.integers(0, rooms[0] * rooms[1], n)
    ix, iy = room % rooms[0], room // rooms[0]
    inner = rng.uniform(1.2, size_m - 1.2, (n, 2))
    return np.column_stack([ix * size_m + inner[:, 0], iy * size_m + inner[:, 1]])


def run(
    *,
    places: int,
    queries: int,
    offsets: list[float],
    seed: int,
    width: int,
    config: SignatureConfig | None = None,
) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    rooms, size = (3, 3), 6.0
    tw = make_textured_world(
        make_world(rooms=rooms, room_size_m=size, landmarks=9, rng=rng), rng=rng
    )
    camera = PanoramaCamera(width=width, height=width // 4)
    xy = place_poses(places, rooms, size, rng)
    cfg = config or SignatureConfig()
    index = AppearanceIndex(cfg)
    sig_ms = []
    for p in xy:
        image = render_panorama(tw, (p[0], p[1], 0.0), camera)[0]
        t0 = time.perf_counter()
        sig = signature(image, cfg)
        sig_ms.append(1e3 * (time.perf_counter() - t0))
        index.add(sig)
    rows: list[dict[str, Any]] = []
    match_ms = []
    for offset in offsets:
        for i, p in enumerate(xy):
            for _ in range(queries):
                yaw = rng.uniform(-math.pi, math.pi)
                a = rng.uniform(-math.pi, math.pi)
                pose = (p[0] + offset * math.cos(a), p[1] + offset * math.sin(a), yaw)
                image, light = relight(render_panorama(tw, pose, camera)[0], rng)
                t0 = time.perf_counter()
                found = index.match(signature(image, cfg))
                match_ms.append(1e3 * (time.perf_counter() - t0))
                best = int(found.order[0])
                nearest = int(np.argmin(np.hypot(*(xy - np.array(pose[:2])).T)))
                rows.append(
                    {
                        "offset_m": offset,
                        "place": i,
                        "nearest": nearest,
                        "found": best,
                        "top1": best == nearest,
                        "top1_own_place": best == i,
                        "score": float(found.scores[best]),
                        "yaw_error_deg": math.degrees(
                            abs(wrap_angle(float(found.yaw_offsets_rad[nearest]) - yaw))
                        ),
                        **light,
                    }
                )
    by_offset = {}
    for offset in offsets:
        sel = [r for r in rows if r["offset_m"] == offset]
        ok = [r for r in sel if r["top1"]]
        by_offset[str(offset)] = {
            "queries": len(sel),
            "top1": float(np.mean([r["top1"] for r in sel])),
            "top1_own_place": float(np.mean([r["top1_own_place"] for r in sel])),
            "yaw_error_deg_median": float(np.median([r["yaw_error_deg"] for r in ok]))
            if ok
            else None,
            "yaw_error_deg_p95": float(np.percentile([r["yaw_error_deg"] for r in ok], 95))
            if ok
            else None,
        }
    return {
        "world": "3x3 rooms of 6 m, rendered panoramas",
        "signature": {"columns": cfg.columns, "bands": cfg.bands},
        "camera": {"width": camera.width, "height": camera.height},
        "places": places,
        "queries_per_place_and_offset": queries,
        "signature_ms_median": float(np.median(sig_ms)),
        "match_ms_median_all_places": float(np.median(match_ms)),
        "by_offset": by_offset,
        "runs": rows,
    }


def timing_100_places(seed: int) -> dict[str, float]:
    """Match time against 100 places (random signatures: the cost does not depend on them)."""
    rng = np.random.default_rng(seed)
    index = AppearanceIndex()
    shape = (index.config.bands, index.config.columns)
    for _ in range(100):
        index.add(rng.standard_normal(shape).astype(np.float32))
    query = rng.standard_normal(shape).astype(np.float32)
    ms = []
    for _ in range(200):
        t0 = time.perf_counter()
        index.match(query)
        ms.append(1e3 * (time.perf_counter() - t0))
    return {"places": 100, "match_ms_median": float(np.median(ms))}


def plot(doc: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    res = doc["recognition"]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    offs = sorted(res["by_offset"], key=float)
    axes[0].plot([float(o) for o in offs], [100 * res["by_offset"][o]["top1"] for o in offs], "o-")
    axes[0].axhline(99, color="r", ls="--", label="goal 99 %")
    axes[0].set_xlabel("query distance from the place, m")
    axes[0].set_ylabel("top-1, %")
    axes[0].set_title(f"{res['places']} places, any yaw, lighting changed")
    axes[0].legend()
    errs = [r["yaw_error_deg"] for r in res["runs"] if r["top1"]]
    axes[1].hist(np.minimum(errs, 10.0), bins=40)
    axes[1].set_xlabel("yaw error of the matched offset, deg (clipped at 10)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--places", type=int, default=36)
    parser.add_argument("--queries", type=int, default=10)
    parser.add_argument("--offsets", type=float, nargs="*", default=[0.0, 0.25, 0.5, 1.0])
    parser.add_argument("--width", type=int, default=512)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--columns", type=int, default=256)
    parser.add_argument("--bands", type=int, default=8)
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    args = parser.parse_args()
    doc: dict[str, Any] = {
        "when": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "load_average_before": [round(v, 2) for v in os.getloadavg()],
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
    }
    doc["recognition"] = run(
        places=args.places,
        queries=args.queries,
        offsets=args.offsets,
        seed=args.seed,
        width=args.width,
        config=SignatureConfig(columns=args.columns, bands=args.bands),
    )
    doc["timing"] = timing_100_places(args.seed)
    doc["load_average_after"] = [round(v, 2) for v in os.getloadavg()]
    summary = {k: v for k, v in doc["recognition"].items() if k != "runs"}
    print(json.dumps({**summary, "timing": doc["timing"]}, indent=1))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "place_recognition.json").write_text(json.dumps(doc, indent=1))
    plot(doc, args.out / "place_recognition.png")


if __name__ == "__main__":
    main()
