"""Snapshot and restore of a `BearingSlam`: everything but iSAM2 itself, as bytes.

iSAM2 does not serialise (GTSAM-NOTES, "Threads and persistence"), but its
factors and linearisation point do. A snapshot stores the current factors as one
``NonlinearFactorGraph`` (``.serialize()``; a ``LinearContainerFactor`` keeps its
own linearisation point), the linearisation point as ``Values``, and the
bookkeeping of `BearingSlam` (robots and their pose windows, landmark records,
candidate tracks, trajectory arrays, removal log tail, the policy's rng state).
`restore` builds a fresh iSAM2 from the factors at the stored linearisation
point in one update, so the estimate after a restore equals the one before up to
iSAM2's relinearisation state (one full step from the same linearisation point).

The blob is a pickle: it is meant for the service's own store, never for data
from outside (imports replay frames instead).
"""

from __future__ import annotations

import pickle
from array import array
from collections import deque
from collections.abc import Callable
from typing import Any

import gtsam
import numpy as np

from graph.factors import pose_key
from graph.slam import BearingSlam, RemovalRecord

SNAPSHOT_VERSION = 1

SLAM_ATTRIBUTES = frozenset(
    {
        # captured
        "config", "_rng", "_graph", "_robots", "_landmarks", "_label_to_id", "_candidates",
        "_next_landmark_id", "_frames", "removals", "removal_count", "_traj_robot",
        "_traj_seq", "_traj_stamp", "_traj_pose", "_live_frames",
        # derived or given again on restore
        "_policy", "_removal_sink",
    }
)  # fmt: skip
"""Every attribute of a BearingSlam that `capture`/`restore` account for. A test checks
this against a live instance, so a new attribute cannot be silently left out."""
GRAPH_ATTRIBUTES = frozenset({"_isam", "_factors", "_key_factors", "_estimate"})
"""Every attribute of an IncrementalGraph; iSAM2 and the index are rebuilt, the
estimate cache is dropped."""


class SnapshotError(ValueError):
    """A snapshot could not be read (wrong version or corrupt)."""


def capture(slam: BearingSlam) -> bytes:
    """The estimator's whole state as bytes (see the module docstring)."""
    inner = slam.graph
    factors = gtsam.NonlinearFactorGraph()
    for index in sorted(inner._factors):
        factors.add(inner._factors[index])
    linpoint = inner.linearization_point() if inner.num_factors else gtsam.Values()
    state: dict[str, Any] = {
        "version": SNAPSHOT_VERSION,
        "config": slam.config,
        "rng": slam._rng.bit_generator.state,
        "factors": factors.serialize(),
        "linpoint": linpoint.serialize(),
        "robots": slam._robots,
        "landmarks": slam._landmarks,
        "label_to_id": slam._label_to_id,
        "candidates": slam._candidates,
        "next_landmark_id": slam._next_landmark_id,
        "frames": slam._frames,
        "removals": list(slam.removals),
        "removal_memory": slam.removals.maxlen,
        "removal_count": slam.removal_count,
        "traj_robot": slam._traj_robot.tobytes(),
        "traj_seq": slam._traj_seq.tobytes(),
        "traj_stamp": slam._traj_stamp.tobytes(),
        "traj_pose": slam._traj_pose.tobytes(),
        "live_frames": slam._live_frames,
    }
    return pickle.dumps(state, protocol=pickle.HIGHEST_PROTOCOL)


def restore(
    blob: bytes, *, removal_sink: Callable[[RemovalRecord], None] | None = None
) -> BearingSlam:
    """A working `BearingSlam` from `capture`'s bytes; iSAM2 is rebuilt from the factors."""
    try:
        state = pickle.loads(blob)
    except Exception as exc:  # pickle raises many types on corrupt input
        raise SnapshotError(f"corrupt snapshot: {exc}") from exc
    if not isinstance(state, dict) or state.get("version") != SNAPSHOT_VERSION:
        raise SnapshotError(f"unsupported snapshot version {state.get('version')!r}")
    rng = np.random.default_rng()
    rng.bit_generator.state = state["rng"]
    slam = BearingSlam(
        state["config"],
        rng=rng,
        removal_sink=removal_sink,
        removal_memory=state["removal_memory"],
    )
    factors = gtsam.NonlinearFactorGraph()
    factors.deserialize(state["factors"])
    if factors.size():
        linpoint = gtsam.Values()
        linpoint.deserialize(state["linpoint"])
        slam.graph.update([factors.at(i) for i in range(factors.size())], linpoint)
    slam._robots = state["robots"]
    slam._landmarks = state["landmarks"]
    slam._label_to_id = state["label_to_id"]
    slam._candidates = state["candidates"]
    slam._next_landmark_id = state["next_landmark_id"]
    slam._frames = state["frames"]
    slam.removals = deque(state["removals"], maxlen=state["removal_memory"])
    slam.removal_count = state["removal_count"]
    slam._traj_robot = array("i", state["traj_robot"])
    slam._traj_seq = array("q", state["traj_seq"])
    slam._traj_stamp = array("d", state["traj_stamp"])
    slam._traj_pose = array("d", state["traj_pose"])
    slam._live_frames = state["live_frames"]
    return slam


def latest_pose_keys(slam: BearingSlam) -> dict[str, int]:
    """The graph key of each robot's newest pose (always still in the graph)."""
    return {
        name: pose_key(robot.slot, robot.next_index - 1) for name, robot in slam._robots.items()
    }


def last_accepted(slam: BearingSlam) -> dict[str, tuple[int, float]]:
    """Each robot's last accepted (seq, stamp)."""
    return {name: (r.last_seq, r.last_stamp) for name, r in slam._robots.items()}
