"""A frame's result document and its events, from the map pipeline's `FrameStep`.

The result is stored as JSON text with the frame in the log, and an idempotent retry
returns those bytes: the document's members and their order are part of the REST
contract. `FrameResult` describes them (the API's response model); every result is
checked against it before it is stored.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, Field

from graph.slam import BearingSlam, RemovalRecord
from service.pipeline import FrameStep

COV3 = (
    "3x3 covariance of (x [m], y [m], theta [rad]) of the pose, x/y in the map frame, "
    "row-major, units m², m·rad, rad²"
)


class PoseXYTheta(BaseModel):
    """A pose in the map frame."""

    x: float = Field(description="metres, map frame")
    y: float = Field(description="metres, map frame")
    theta: float = Field(
        description="yaw, radians, counter-clockwise from the map's +x axis, in (-pi, pi]"
    )


class Localisation(BaseModel):
    status: Literal["initialising", "tracking", "lost", "relocalised"] = Field(
        description="initialising (no pose yet: the filter searches), tracking (the graph "
        "tracks the robot), lost (graph and filter disagree: the filter re-localises), "
        "relocalised (this frame anchored the robot's pose chain at the filter's estimate)"
    )
    place: int | None = Field(None, description="id of the current place, if any")
    confidence: float | None = Field(None, description="confidence in [0, 1], if known")


class LandmarkChanges(BaseModel):
    observed: list[int] = Field(description="ids of live landmarks observed in this frame")
    added: list[int] = Field(description="ids of landmarks this frame initialised")
    marginalised: list[int] = Field(
        description="ids the landmark budget removed after it, or, with the map's "
        "solver.upkeep after the frame (new maps: 'budget_after_frame'), after the frame "
        "before it"
    )
    live: int = Field(
        description="live landmarks after the frame (with solver.upkeep after the frame, "
        "before the removals that follow it)"
    )


class FrameResult(BaseModel):
    """What one frame did to the map."""

    frame_id: int = Field(description="position of the frame in the map's log (1-based)")
    robot: str = Field(description="robot name, as posted")
    seq: int = Field(description="seq, as posted")
    stamp: float = Field(description="seconds, as posted")
    pose: PoseXYTheta = Field(description="the robot's estimated pose at this frame")
    covariance: list[list[float]] | None = Field(description=COV3)
    localisation: Localisation = Field(description="localisation status of the robot")
    landmarks: LandmarkChanges = Field(description="what the frame did to the landmarks")
    timing_ms: dict[str, float] = Field(
        description="worker time per stage, milliseconds (prepare, update, budget, "
        "covariance, total; log = parse, checks and the committed append to the durable log; "
        "image frames also: decode = PNG/JPEG decoding + validation (+ omni unwrap) and "
        "features = feature extraction, both in the helper thread, "
        "features_wait = how long the frame waited for them after logging, association)"
    )


@dataclass(frozen=True)
class FrameReply:
    """A map session's answer to a frame (`MapSession.submit`)."""

    result_json: str
    """The frame result (a `FrameResult`, checked when it was made) as JSON text, exactly
    as stored: an idempotent retry answers these bytes."""
    replayed: bool = False
    """An idempotent retry, answered from the log."""
    events: list[tuple[int, str, str]] = field(default_factory=list)
    """The events the frame stored: (id, kind, data JSON), oldest first (the event
    streams send them)."""
    timing_ms: dict[str, float] = field(default_factory=dict)
    """The result's worker timings, ms (empty for a retry)."""
    store_ms: float = 0.0
    """Storing the result, events and removals, ms."""
    live: int = 0
    """Live landmarks after the frame."""
    marginalised: int = 0
    """Landmarks the budget removed after the frame."""


def result_doc(
    slam: BearingSlam, step: FrameStep, log_id: int, timing: dict[str, float]
) -> dict[str, Any]:
    """The frame result (checked against `FrameResult`: a ValueError names a member
    that does not fit); `timing` the runtime's own timings (ms) besides the pipeline's."""
    outcome = step.outcome
    pose = step.pose
    doc = {
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
    FrameResult.model_validate(doc)
    return doc


def frame_events(
    slam: BearingSlam,
    step: FrameStep,
    result_json: str,
    removals: list[RemovalRecord],
    log_id: int,
) -> tuple[list[tuple[str, str]], list[tuple[int, int, str]], list[tuple[int, int, str]]]:
    """(events as (type, JSON data), removal rows, archived landmark rows) of a frame."""
    events: list[tuple[str, str]] = [("frame", result_json)]
    # Removals made after the frame before (SlamConfig.upkeep "after_frame") happened
    # before this frame's restorations: their events come first.
    index = None if step.outcome is None else step.outcome.frame_index
    earlier = [r for r in removals if index is not None and r.frame < index]
    rows, archived = _removal_events(slam, earlier, log_id, events)
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
    own = [r for r in removals if index is None or r.frame >= index]
    more_rows, more_archived = _removal_events(slam, own, log_id, events)
    return events, rows + more_rows, archived + more_archived


def _removal_events(
    slam: BearingSlam, removals: list[RemovalRecord], log_id: int, events: list[tuple[str, str]]
) -> tuple[list[tuple[int, int, str]], list[tuple[int, int, str]]]:
    """Append the removals' events to `events`; their removal rows and archived rows."""
    rows = []
    archived = []
    for r in removals:
        doc = {**r.as_dict(), "frame_id": log_id}
        events.append(("landmark_marginalised", json.dumps(doc)))
        rows.append((r.landmark_id, r.frame, json.dumps(doc)))
        entry = slam.archive.get(r.landmark_id)
        if entry is not None:
            archived.append((r.landmark_id, r.frame, json.dumps(entry.as_dict())))
    return rows, archived


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
