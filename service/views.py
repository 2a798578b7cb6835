"""The reads of a map that need its store besides the estimator: trajectories (with
frame figures) and coverage. Units metres, radians, seconds; covariances as nested
lists, row-major."""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from graph.slam import BearingSlam
from graph.trajectory import with_final_rows
from service.errors import unknown_robot
from service.pipeline.coverage import coverage_grid
from service.pipeline.documents import clusters_doc, landmark_table, trajectory_rows
from service.store import FrameFigures
from service.store_sql import MapStore


def trajectory_doc(
    slam: BearingSlam, store: MapStore, map_id: str, robot: str | None = None
) -> dict[str, list[dict[str, float]]]:
    """Every frame's pose per robot: [{seq, stamp, x, y, theta}]."""
    if robot is not None and robot not in slam.robots:
        raise unknown_robot(map_id, robot, " (GET /pose lists its robots)")
    stored = store.poses(robot)  # the final rows; the estimator holds the newer ones
    return {
        name: trajectory_rows(with_final_rows(stored.get(name), held))
        for name, held in slam.trajectory(robot).items()
    }


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
