"""Which step of a frame makes the lifelong run's peak RSS: a memory attribution probe.

The lifelong goal reads the *peak* RSS (ru_maxrss), and a peak is made by transients:
memory a step allocates and frees within one frame. This probe replays the lifelong
simulation's bounded run (bench.lifelong: same world, seed and configuration) in-process
and measures, for every frame and for the steps inside it, how far the resident
high-water mark (``VmHWM``, restarted through ``/proc/self/clear_refs``) rose above the
RSS the step started from:

- ``frame``: ``BearingSlam.process``;
- ``budget`` / ``thin``: the landmark removals of a frame (with the keyframes a removal
  thins in its own update) / the thinning of keyframes whose factor grew otherwise;
- ``update``: ``IncrementalGraph.update`` (the Schur complement plus iSAM2's update);
- ``schur``: ``IncrementalGraph._schur_complement``, and in it ``linearise``
  (``NonlinearFactorGraph.linearize``) and ``eliminate``
  (``GaussianFactorGraph.eliminatePartialMultifrontal``);
- ``covariance``: the landmarks' joint marginal for the policy.

Scopes nest: before a step restarts the high-water mark, the mark so far is folded into
every open scope, so an outer scope's figure includes its steps'. The steps are wrapped
by patching the classes for this process only; the figures are the same computation as
the lifelong run's, not its timing (the probe's wrappers and records add to the RSS, so
its steady RSS is not quite the lifelong run's). Linux only (VmHWM, clear_refs).

    python -m bench.memory_transients [--frames 8000] [--out bench/results]
"""

from __future__ import annotations

import argparse
import functools
import heapq
import json
import sys
import time
from array import array
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gtsam
import numpy as np

from bench.lifelong import RUNS, SEED, machine_info, make_run
from graph.isam import IncrementalGraph
from graph.slam import BearingSlam
from service.offline.replay import current_rss_mb, reset_peak_rss

TOP_FRAMES = 12
"""Frames with the largest transients listed with their steps."""


def high_water_mb() -> float:
    """VmHWM: the resident high-water mark since the last reset, MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError("no VmHWM in /proc/self/status")


class Probe:
    """Nested scopes, each measuring its rise of the high-water mark above its start."""

    def __init__(self) -> None:
        self._open: list[list[Any]] = []  # [name, rss at start, high water, t0, detail]
        self.steps: list[dict[str, Any]] = []

    def _fold(self) -> None:
        mark = high_water_mb()
        for scope in self._open:
            scope[2] = max(scope[2], mark)

    def enter(self, name: str, detail: dict[str, Any] | None = None) -> None:
        self._fold()
        rss = current_rss_mb()
        if not reset_peak_rss():
            raise RuntimeError("this kernel cannot reset the peak RSS (/proc/self/clear_refs)")
        self._open.append([name, rss, rss, time.perf_counter(), detail or {}])

    def leave(self) -> dict[str, Any]:
        self._fold()
        name, rss, mark, t0, detail = self._open.pop()
        reset_peak_rss()
        step = {
            "step": name,
            "transient_mb": round(mark - rss, 2),
            "retained_mb": round(current_rss_mb() - rss, 2),
            "ms": round(1e3 * (time.perf_counter() - t0), 1),
            **detail,
        }
        self.steps.append(step)
        return step

    def wrap(
        self, owner: Any, attr: str, name: str, detail: Callable[..., dict[str, Any]] | None = None
    ) -> None:
        """Measure every call of owner.attr as scope `name` (`detail` of its arguments)."""
        original = getattr(owner, attr)

        @functools.wraps(original)
        def measured(*args: Any, **kwargs: Any) -> Any:
            self.enter(name, detail(*args, **kwargs) if detail else None)
            try:
                return original(*args, **kwargs)
            finally:
                self.leave()

        setattr(owner, attr, measured)


def _schur_detail(graph: IncrementalGraph, keys: list[int], *_: Any, **__: Any) -> dict[str, Any]:
    """How big the marginalisation is: keys eliminated, factors and keys it touches."""
    indices = {i for k in keys for i in graph.factors_of(k)}
    touched = {k for i in indices for k in graph.factor_keys(i)}
    largest = max((len(graph.factor_keys(i)) for i in indices), default=0)
    return {
        "eliminated": len(keys),
        "factors": len(indices),
        "keys": len(touched),
        "largest_factor_keys": largest,
    }


def instrument(probe: Probe) -> None:
    probe.wrap(BearingSlam, "_enforce_budget", "budget")
    probe.wrap(BearingSlam, "_thin_keyframes", "thin")
    probe.wrap(IncrementalGraph, "update", "update")
    probe.wrap(IncrementalGraph, "_schur_complement", "schur", _schur_detail)
    probe.wrap(IncrementalGraph, "landmark_covariances", "covariance")
    probe.wrap(gtsam.NonlinearFactorGraph, "linearize", "linearise")
    probe.wrap(gtsam.GaussianFactorGraph, "eliminatePartialMultifrontal", "eliminate")


def summarise(values: array[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=np.float64)
    return {
        "count": len(a),
        "max_mb": round(float(a.max()), 2),
        "p999_mb": round(float(np.quantile(a, 0.999)), 2),
        "p99_mb": round(float(np.quantile(a, 0.99)), 2),
        "median_mb": round(float(np.median(a)), 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=8000)
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    args = parser.parse_args()
    run = make_run(20_000, SEED)  # the lifelong run's frames (its first --frames)
    todo = run.frames[: args.frames]
    del run
    probe = Probe()
    instrument(probe)
    slam = BearingSlam(RUNS["bounded"], rng=np.random.default_rng(SEED))
    # Per-frame figures in typed arrays and only the worst frames in full: the probe's
    # own records are inside the RSS it measures.
    transients: array[float] = array("d")
    by_step: dict[str, array[float]] = {}
    schur_keys: array[int] = array("i")  # per frame: the most keys one Schur complement touched
    factor_keys: array[int] = array("i")  # per frame: the most keys of a factor it took in
    worst_heap: list[tuple[float, int, dict[str, Any]]] = []
    start = time.perf_counter()
    for i, frame in enumerate(todo):
        probe.steps = []
        probe.enter("frame")
        slam.process(frame, with_covariance=False)
        whole = probe.leave()
        transients.append(whole["transient_mb"])
        for step in probe.steps:
            by_step.setdefault(step["step"], array("d")).append(step["transient_mb"])
        schurs = [s for s in probe.steps if s["step"] == "schur"]
        schur_keys.append(max((s["keys"] for s in schurs), default=0))
        factor_keys.append(max((s["largest_factor_keys"] for s in schurs), default=0))
        if len(worst_heap) < TOP_FRAMES or whole["transient_mb"] > worst_heap[0][0]:
            inner = sorted(probe.steps[:-1], key=lambda s: -s["transient_mb"])[:4]
            record = {"frame": i, **whole, "rss_after_mb": round(current_rss_mb(), 2), "top": inner}
            heapq.heappush(worst_heap, (whole["transient_mb"], i, record))
            if len(worst_heap) > TOP_FRAMES:
                heapq.heappop(worst_heap)
        if (i + 1) % 1000 == 0:
            print(
                f"frame {i + 1:6d}  rss {current_rss_mb():7.1f} MiB"
                f"  {time.perf_counter() - start:6.1f} s",
                file=sys.stderr,
                flush=True,
            )
    worst = [record for *_, record in sorted(worst_heap, reverse=True)]
    steps = {name: summarise(v) for name, v in sorted(by_step.items())}
    blocks = 1000
    doc = {
        "benchmark": "memory transients of the lifelong bounded run, by step",
        "frames": args.frames,
        "config": f"bench.lifelong RUNS['bounded'], seed {SEED}",
        "steps": steps,
        "worst_frames": worst,
        "per_block": [
            {
                "frames": [b, b + blocks],
                "max_transient_mb": max(transients[b : b + blocks]),
                "max_schur_keys": max(schur_keys[b : b + blocks], default=0),
                "max_factor_keys": max(factor_keys[b : b + blocks], default=0),
            }
            for b in range(0, len(transients), blocks)
        ],
        "machine": machine_info(),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "memory_transients.json"
    path.write_text(json.dumps(doc, indent=1))
    print("MiB above the step's start:")
    print(f"{'step':12s} {'count':>7s} {'max':>7s} {'p99.9':>7s} {'p99':>7s}")
    for name, st in steps.items():
        print(
            f"{name:12s} {st['count']:7d} {st['max_mb']:7.2f}"
            f" {st['p999_mb']:7.2f} {st['p99_mb']:7.2f}"
        )
    print("worst frames:")
    for f in worst:
        parts = ", ".join(f"{s['step']} {s['transient_mb']}" for s in f["top"])
        print(f"  {f['frame']:6d}  {f['transient_mb']:6.2f} MiB  ({parts})")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
