"""The map's state as the documents its reads answer with, from the estimator alone:
each robot's latest pose, the live landmarks with their coverage clusters, and
trajectory rows. Units metres, radians, seconds; covariances as nested lists,
row-major."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from graph.policies import LandmarkTable, coverage_clusters, information_content
from graph.slam import BearingSlam
from graph.snapshot import last_accepted


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


def trajectory_rows(rows: NDArray[np.float64]) -> list[dict[str, float]]:
    """(N, 5) rows seq, stamp, x, y, theta as [{seq, stamp, x, y, theta}]."""
    return [
        {"seq": int(r[0]), "stamp": float(r[1]), "x": r[2], "y": r[3], "theta": r[4]}
        for r in rows.tolist()
    ]


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
