"""Snapshot and restore of a `BearingSlam`: everything but iSAM2 itself, as bytes.

iSAM2 does not serialise (GTSAM-NOTES, "Threads and persistence"), but its
factors and linearisation point do. A snapshot stores the current factors as one
``NonlinearFactorGraph`` (``.serialize()``; a ``LinearContainerFactor`` keeps its
own linearisation point; a relative marginal, whose error is a Python callback,
is stored as its `RelativeSpec`), the linearisation point as ``Values``, and the
bookkeeping of `BearingSlam` (robots and their pose windows, landmark records,
candidate tracks, the archive of removed landmarks, the trajectory rows it holds, removal log
tail, the policy's rng state).
`restore` builds a fresh iSAM2 from the factors at the stored linearisation
point in one update, so the estimate after a restore equals the one before up to
iSAM2's relinearisation state (one full step from the same linearisation point).

The blob is a pickle: it is meant for the service's own store, never for data
from outside (imports replay frames instead).
"""

from __future__ import annotations

import pickle
from collections.abc import Callable
from dataclasses import asdict, fields
from typing import Any

import gtsam
import numpy as np

from graph.config import SlamConfig
from graph.relative import RelativeMarginalFactor, RelativeSpec
from graph.slam import BearingSlam, RemovalRecord
from graph.trajectory import PoseRow

SNAPSHOT_VERSION = 5
"""3: the trajectory is a graph.trajectory.Trajectory (held rows + kept final rows).
4: the estimator keeps its removed landmarks in a graph.archive.LandmarkArchive.
5: the config is kept by field name (a pickled SlamConfig is positional: a field added
in the middle shifted every later one), with the frame whose upkeep is pending."""

_SLAM_SPECIAL = frozenset({"_graph", "_policy", "_removal_sink", "_rng", "_trajectory_sink"})
"""BearingSlam attributes handled explicitly: the graph is rebuilt, the policy is
derived from the config, the sinks are given again, the rng keeps its state."""
_GRAPH_SPECIAL = frozenset(
    {"_isam", "_theta", "_config", "_factors", "_key_factors", "_estimate", "_points", "_poses"}
)
"""IncrementalGraph attributes rebuilt by re-adding the factors (the estimate cache is
dropped; the linearisation point is the new iSAM2's; the config is the estimator's)."""


class SnapshotError(ValueError):
    """A snapshot could not be taken or read (unpicklable state, wrong version, corrupt)."""


def capture(slam: BearingSlam, *, extra: Any = None) -> bytes:
    """The estimator's whole state as bytes (see the module docstring); `extra` is any
    picklable state kept beside it (e.g. the place localiser's), see `restore_with_extra`.

    Every attribute of the estimator and of its graph that is not rebuilt on restore
    is pickled as it is (plain Python and numpy bookkeeping), so state added to
    `BearingSlam` later is carried without changes here.
    """
    inner = slam.graph
    factors = gtsam.NonlinearFactorGraph()
    relative: list[RelativeSpec] = []
    for index in sorted(inner._factors):
        factor = inner._factors[index]
        if isinstance(factor, RelativeMarginalFactor):  # a Python callback: keep its data
            relative.append(factor.spec)
        else:
            factors.add(factor)
    linpoint = inner.linearization_point() if inner.num_factors else gtsam.Values()
    state: dict[str, Any] = {
        "version": SNAPSHOT_VERSION,
        "rng": slam._rng.bit_generator.state,
        "factors": factors.serialize(),
        "relative": relative,
        "linpoint": linpoint.serialize(),
        "slam": {
            **{k: v for k, v in vars(slam).items() if k not in _SLAM_SPECIAL},
            "config": asdict(slam.config),
        },
        "graph": {k: v for k, v in vars(inner).items() if k not in _GRAPH_SPECIAL},
        "extra": extra,
    }
    try:
        return pickle.dumps(state, protocol=pickle.HIGHEST_PROTOCOL)
    except (TypeError, pickle.PicklingError) as exc:
        raise SnapshotError(f"estimator state does not pickle: {exc}") from exc


def restore(
    blob: bytes,
    *,
    removal_sink: Callable[[RemovalRecord], None] | None = None,
    trajectory_sink: Callable[[list[PoseRow]], None] | None = None,
) -> BearingSlam:
    """A working `BearingSlam` from `capture`'s bytes; iSAM2 is rebuilt from the factors.
    The sinks are `BearingSlam`'s (a trajectory sink receives only rows that become final
    after the restore: the snapshot holds those that were held when it was taken)."""
    return restore_with_extra(blob, removal_sink=removal_sink, trajectory_sink=trajectory_sink)[0]


def restore_with_extra(
    blob: bytes,
    *,
    removal_sink: Callable[[RemovalRecord], None] | None = None,
    trajectory_sink: Callable[[list[PoseRow]], None] | None = None,
) -> tuple[BearingSlam, Any]:
    """`restore`, and the `extra` state given to `capture` (None if none)."""
    try:
        state = pickle.loads(blob)
    except Exception as exc:  # pickle raises many types on corrupt input
        raise SnapshotError(f"corrupt snapshot: {exc}") from exc
    if not isinstance(state, dict) or state.get("version") != SNAPSHOT_VERSION:
        version = state.get("version") if isinstance(state, dict) else None
        raise SnapshotError(f"unsupported snapshot version {version!r}")
    plain: dict[str, Any] = state["slam"]
    rng = np.random.default_rng()
    rng.bit_generator.state = state["rng"]
    known = {f.name for f in fields(SlamConfig)}
    plain["config"] = SlamConfig(**{k: v for k, v in plain["config"].items() if k in known})
    slam = BearingSlam(
        plain["config"],
        rng=rng,
        removal_sink=removal_sink,
        removal_memory=plain["removals"].maxlen,
        trajectory_sink=trajectory_sink,
    )
    factors = gtsam.NonlinearFactorGraph()
    factors.deserialize(state["factors"])
    rebuilt = [factors.at(i) for i in range(factors.size())]
    rebuilt += [RelativeMarginalFactor(spec) for spec in state["relative"]]
    if rebuilt:
        linpoint = gtsam.Values()
        linpoint.deserialize(state["linpoint"])
        slam.graph.update(rebuilt, linpoint)
    for name, value in state["graph"].items():
        setattr(slam.graph, name, value)
    for name, value in plain.items():
        setattr(slam, name, value)
    return slam, state.get("extra")


def last_accepted(slam: BearingSlam) -> dict[str, tuple[int, float]]:
    """Each robot's last accepted (seq, stamp)."""
    return {name: (r.last_seq, r.last_stamp) for name, r in slam._robots.items()}
