"""Read-only views of a map for the API: poses, trajectories (with frame figures),
landmarks, coverage.

Functions of the estimator (and the store, for the removal log); units metres,
radians, seconds; covariances as nested lists, row-major.
"""

from __future__ import annotations

import io
import json
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from graph.policies import LandmarkTable, coverage_clusters, information_content
from graph.slam import BearingSlam
from graph.snapshot import last_accepted
from graph.trajectory import with_final_rows
from service.errors import ServiceError
from service.pipeline.coverage import coverage_grid
from service.store import FrameFigures
from service.store_sql import MapStore
from service.tum import Trajectory, write_tum


def pose_doc(slam: BearingSlam, map_id: str, only: str | None = None) -> dict[str, Any]:
    """Latest pose of each robot (`only`: of that robot, if it has one) with its (3, 3)
    covariance."""
    last = last_accepted(slam)
    robots = {}
    for name in slam.robots:
        if only is not None and name != only:
            continue
        p = slam.latest_pose(name)
        cov = slam.latest_pose_covariance(name)
        robots[name] = {
            "seq": last[name][0],
            "stamp": last[name][1],
            "pose": {"x": float(p.x()), "y": float(p.y()), "theta": float(p.theta())},
            "covariance": np.asarray(cov).tolist(),
            "localisation": {"status": "tracking", "place": None, "confidence": None},
        }
    return {"map_id": map_id, "robots": robots}


def full_trajectory(
    slam: BearingSlam, store: MapStore, robot: str | None = None
) -> dict[str, NDArray[np.float64]]:
    """Every frame's row per robot (seq, stamp, x, y, theta; sorted by seq): the final
    rows in the store and the rows the estimator still holds."""
    stored = store.poses(robot)
    return {
        name: with_final_rows(stored.get(name), held)
        for name, held in slam.trajectory(robot).items()
    }


def trajectory_doc(
    slam: BearingSlam, store: MapStore, map_id: str, robot: str | None = None
) -> dict[str, list[dict[str, float]]]:
    """Every frame's pose per robot: [{seq, stamp, x, y, theta}]."""
    if robot is not None and robot not in slam.robots:
        raise ServiceError(
            404,
            "unknown-robot",
            "Unknown robot",
            f"robot: map {map_id!r} has no robot {robot!r} (GET /pose lists its robots)",
            field="robot",
        )
    return {
        name: trajectory_rows(rows) for name, rows in full_trajectory(slam, store, robot).items()
    }


def final_before_held(
    final: NDArray[np.float64] | None, held: NDArray[np.float64] | None
) -> NDArray[np.float64]:
    """One robot's rows by seq: the stored final rows older than the first held row (the
    store may already have made final a row a newer frame took from the held ones) and
    the held rows."""
    parts = []
    if final is not None and len(final):
        parts.append(final if held is None or not len(held) else final[final[:, 0] < held[0, 0]])
    if held is not None and len(held):
        parts.append(held)
    if not parts:
        return np.zeros((0, 5), dtype=np.float64)
    return np.concatenate(parts)


def trajectory_rows(rows: NDArray[np.float64]) -> list[dict[str, float]]:
    """(N, 5) rows seq, stamp, x, y, theta as [{seq, stamp, x, y, theta}]."""
    return [
        {"seq": int(r[0]), "stamp": float(r[1]), "x": r[2], "y": r[3], "theta": r[4]}
        for r in rows.tolist()
    ]


def attach_frame_stats(
    robots: dict[str, list[dict[str, Any]]],
    stats: list[FrameFigures],
    labels: dict[int, str],
    *,
    every: int,
) -> None:
    """Add frame figures to every `every`-th pose of each robot and to its latest, in place.

    `stats` are `MapStore.frame_stats` rows in log order; `labels` maps every landmark
    id the map ever had to its label. Each chosen trajectory row gains ``frame_id``,
    ``covariance`` (3x3, as the frame's result reported it when the frame was
    processed), ``live``, ``ms`` and ``uncapped``: the landmarks there would be without
    the cap, i.e. the distinct labels among the landmarks initialised up to that frame
    (one seen again after its removal comes back under its id; re-triangulated under a
    new id instead, with SlamConfig.restore_archived off, it still counts once).
    """
    if every <= 0 or not stats:
        return
    seen_ids: set[int] = set()
    seen_labels: set[str] = set()
    uncapped = []
    for row in stats:
        # a landmark removed by the frame that initialised it is only in `marginalised`
        for lid in (*row.added, *row.marginalised):
            if lid not in seen_ids:
                seen_ids.add(lid)
                seen_labels.add(labels.get(lid, f"id:{lid}"))
        uncapped.append(len(seen_labels))
    by_key = {(row.robot, row.seq): k for k, row in enumerate(stats)}
    for name, rows in robots.items():
        for i, point in enumerate(rows):
            if i % every and i != len(rows) - 1:
                continue
            k = by_key.get((name, int(point["seq"])))
            if k is None:
                continue
            row = stats[k]
            point["frame_id"] = row.frame_id
            cov = row.covariance_json
            point["covariance"] = None if cov is None else json.loads(cov)
            point["live"] = row.live
            point["uncapped"] = uncapped[k]
            point["ms"] = row.total_ms


def landmark_table(slam: BearingSlam) -> tuple[LandmarkTable, np.ndarray]:
    """The live landmarks as the policy sees them, with (N, 2, 2) covariances (m²)."""
    ids = sorted(slam.landmarks)
    records = [slam.landmarks[i] for i in ids]
    cov = slam.landmark_covariances(ids) if ids else np.zeros((0, 2, 2), dtype=np.float64)
    info = information_content(cov) if ids else np.zeros(0)
    table = LandmarkTable(
        ids=np.asarray(ids, dtype=np.int64),
        observed_from=np.array([r.observed_from for r in records]).reshape(-1, 2),
        counts=np.array([r.count for r in records], dtype=np.int64),
        first_seen=np.array([r.added_frame for r in records], dtype=np.int64),
        information=info,
    )
    return table, cov


def clusters_doc(table: LandmarkTable, seed: int) -> tuple[np.ndarray, dict[str, Any] | None]:
    """Coverage clusters (seeded k-means, the map's rng untouched): labels and document."""
    if len(table) == 0:
        return np.zeros(0, dtype=np.int64), None
    clusters = coverage_clusters(table, rng=np.random.default_rng(seed))
    doc = {
        "k": clusters.k,
        "clusters": [
            {
                "index": c,
                "members": [int(i) for i in table.ids[clusters.labels == c]],
                "centre": {
                    "x": float(clusters.centres[c, 0]),
                    "y": float(clusters.centres[c, 1]),
                },
                "spread": float(clusters.spreads[c]),
            }
            for c in range(clusters.k)
        ],
    }
    return clusters.labels, doc


def landmarks_doc(slam: BearingSlam, seed: int) -> list[dict[str, Any]]:
    """Live landmarks: position, covariance, information, E(X), cluster."""
    table, cov = landmark_table(slam)
    labels, _ = clusters_doc(table, seed)
    assert table.information is not None
    out = []
    for row, lid in enumerate(table.ids.tolist()):
        record = slam.landmarks[lid]
        x, y = (float(v) for v in slam.landmark_position(lid))
        out.append(
            {
                "id": lid,
                "label": record.label,
                "x": x,
                "y": y,
                "covariance": cov[row].tolist(),
                "information": float(table.information[row]),
                "observed_from": {
                    "x": float(record.observed_from[0]),
                    "y": float(record.observed_from[1]),
                    "n": record.count,
                },
                "cluster": int(labels[row]),
                "first_stamp": record.first_stamp,
                "last_stamp": record.last_stamp,
            }
        )
    return out


def restored_events(
    slam: BearingSlam, restored: Sequence[int], frame_id: int
) -> list[tuple[str, str]]:
    """`landmark_restored` events {id, label, x, y [m], restorations, frame_id} of the
    landmarks that came back from the archive in a frame (x, y: the estimate after it;
    a landmark the budget removed again in the same frame: its archived one)."""
    events = []
    for lid in restored:
        record = slam.landmarks.get(lid)
        if record is not None:
            x, y = (float(v) for v in slam.landmark_position(lid))
            label, restorations = record.label, record.restorations
        else:
            entry = slam.archive.get(lid)
            assert entry is not None  # removed again: archived again
            (x, y), label, restorations = entry.position, entry.label, entry.restorations
        doc = {
            "id": lid,
            "label": label,
            "x": x,
            "y": y,
            "restorations": restorations,
            "frame_id": frame_id,
        }
        events.append(("landmark_restored", json.dumps(doc)))
    return events


def coverage_doc(
    slam: BearingSlam,
    store: MapStore,
    map_id: str,
    seed: int,
    *,
    cell_m: float,
    radius_m: float,
    removals: int,
) -> dict[str, Any]:
    """Clusters with spreads, each landmark's E(X) and information, grid, removal log."""
    table, _ = landmark_table(slam)
    _, clusters = clusters_doc(table, seed)
    positions = [store.pose_positions(), *(rows[:, 2:4] for rows in slam.trajectory().values())]
    xy = np.concatenate(positions)
    assert table.information is not None
    return {
        "map_id": map_id,
        "live_landmarks": len(table),
        "clusters": clusters["clusters"] if clusters else [],
        "landmarks": [
            {
                "id": int(lid),
                "observed_from": {
                    "x": float(table.observed_from[i, 0]),
                    "y": float(table.observed_from[i, 1]),
                    "n": int(table.counts[i]),
                },
                "information": float(table.information[i]),
            }
            for i, lid in enumerate(table.ids)
        ],
        "grid": coverage_grid(xy, table.observed_from, cell_m=cell_m, radius_m=radius_m),
        "removal_count": store.removal_count(),
        "removals": store.removals(limit=removals),
    }


def tum_text(rows: list[dict[str, float]]) -> str:
    """TUM lines ``stamp x y 0 0 0 qz qw`` of trajectory rows (as `trajectory` returns)."""
    stamps = np.array([r["stamp"] for r in rows], dtype=np.float64)
    poses = np.array([[r["x"], r["y"], r["theta"]] for r in rows], dtype=np.float64)
    buf = io.StringIO()
    write_tum(buf, Trajectory.from_poses(stamps, poses.reshape(-1, 3)))  # type: ignore[arg-type]
    return buf.getvalue()
