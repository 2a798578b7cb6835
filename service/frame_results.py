"""A frame's result document and its events, from the map pipeline's `FrameStep`.

The result is stored as JSON text with the frame in the log, and an idempotent retry
returns those bytes: the document's members and their order are part of the REST
contract (api.models.FrameResult describes them).
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from graph.slam import BearingSlam, RemovalRecord
from service.pipeline import FrameStep
from service.views import restored_events

__all__ = ["frame_events", "result_doc"]


def result_doc(
    slam: BearingSlam, step: FrameStep, log_id: int, timing: dict[str, float]
) -> dict[str, Any]:
    """The frame result; `timing` the runtime's own timings (ms) besides the pipeline's."""
    outcome = step.outcome
    pose = step.pose
    return {
        "frame_id": log_id,
        "robot": step.robot,
        "seq": step.seq,
        "stamp": step.stamp,
        "pose": {"x": pose.x, "y": pose.y, "theta": pose.theta},
        "covariance": np.asarray(step.covariance).tolist(),
        "localisation": {
            "status": step.status,
            "place": step.place,
            "confidence": step.confidence,
        },
        "landmarks": {
            "observed": [] if outcome is None else list(outcome.observed),
            "added": [] if outcome is None else list(outcome.added),
            "marginalised": [] if outcome is None else list(outcome.marginalised),
            "live": len(slam.landmarks),
        },
        "timing_ms": {
            **({} if outcome is None else outcome.timing_ms),
            "localise": step.timing_ms["localise"],
            **timing,
            **{k: v for k, v in step.timing_ms.items() if k != "localise"},
        },
    }


def frame_events(
    slam: BearingSlam,
    step: FrameStep,
    result_json: str,
    removals: list[RemovalRecord],
    log_id: int,
) -> tuple[list[tuple[str, str]], list[tuple[int, int, str]], list[tuple[int, int, str]]]:
    """(events as (type, JSON data), removal rows, archived landmark rows) of a frame."""
    events: list[tuple[str, str]] = [("frame", result_json)]
    added = () if step.outcome is None else step.outcome.added
    if step.learnt is not None:
        doc = {"id": step.learnt.id, "robot": step.learnt.robot}
        events.append(("place_learnt", json.dumps({**doc, "frame_id": log_id})))
    for lid in added:
        if lid in slam.landmarks:
            x, y = (float(v) for v in slam.landmark_position(lid))
            doc = {"id": lid, "label": slam.landmarks[lid].label, "x": x, "y": y}
            events.append(("landmark_added", json.dumps({**doc, "frame_id": log_id})))
    restored = () if step.outcome is None else step.outcome.restored
    events.extend(restored_events(slam, restored, log_id))
    rows = []
    archived = []
    for r in removals:
        doc = {**r.as_dict(), "frame_id": log_id}
        events.append(("landmark_marginalised", json.dumps(doc)))
        rows.append((r.landmark_id, r.frame, json.dumps(doc)))
        entry = slam.archive.get(r.landmark_id)
        if entry is not None:
            archived.append((r.landmark_id, r.frame, json.dumps(entry.as_dict())))
    return events, rows, archived
