"""A map pipeline built afresh or from a snapshot.

A snapshot keeps the pipeline in two parts (the store's snapshot row and its
front-end column): `PipelineState` (the localiser and every robot's state) pickled
beside the estimator (graph.snapshot.capture's `extra`), and a camera map's
associator (landmark views, candidate tracks). Snapshots taken before the pipeline
had its own package still load (service.pipeline.legacy).
"""

from __future__ import annotations

import pickle
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from frontend.association import Associator
from frontend.pipeline import FrontEnd
from graph.slam import BearingSlam, RemovalRecord
from graph.snapshot import capture, restore_with_extra
from graph.trajectory import PoseRow
from service.pipeline.appearance import AppearancePlaces
from service.pipeline.images import ImageFrontEnd
from service.pipeline.legacy import MapLocalisation, older_names, robots_of
from service.pipeline.localiser import PlaceLocaliser
from service.pipeline.map_pipeline import MapPipeline
from service.pipeline.robots import RobotState

__all__ = ["PipelineState", "fresh_pipeline", "restore_pipeline", "snapshot_pipeline"]


@dataclass
class PipelineState:
    """What a snapshot keeps of the pipeline beside the estimator."""

    localiser: PlaceLocaliser
    robots: dict[str, RobotState] = field(default_factory=dict)


def fresh_pipeline(
    slam: BearingSlam, *, seed: int, front_end: FrontEnd | None = None
) -> MapPipeline:
    """A new map's pipeline: its localiser seeded from the map's seed; `front_end` a
    camera map's (its associator starts afresh)."""
    images = None
    if front_end is not None:
        front_end.associator = Associator(front_end.associator.config)
        images = ImageFrontEnd(slam, front_end)
    return MapPipeline(slam, localiser=PlaceLocaliser(seed), images=images)


def snapshot_pipeline(pipeline: MapPipeline) -> tuple[bytes, bytes | None]:
    """(the snapshot of the estimator with the pipeline's state, the front end's state
    (None without a camera))."""
    assert pipeline.localiser is not None
    extra = PipelineState(pipeline.localiser, pipeline.robots)
    blob = capture(pipeline.slam, extra=extra)
    images = pipeline.images
    if images is None:
        return blob, None
    return blob, pickle.dumps({"associator": images.front_end.associator}, protocol=5)


def restore_pipeline(
    blob: bytes,
    frontend: bytes | None,
    *,
    seed: int,
    front_end: FrontEnd | None = None,
    removal_sink: Callable[[RemovalRecord], None] | None = None,
    trajectory_sink: Callable[[list[PoseRow]], None] | None = None,
) -> MapPipeline:
    """The pipeline of `snapshot_pipeline`'s bytes (or an older snapshot's).

    Raises graph.snapshot.SnapshotError, ValueError or an unpickling error when the
    snapshot cannot be read."""
    with older_names():
        slam, extra = restore_with_extra(
            blob, removal_sink=removal_sink, trajectory_sink=trajectory_sink
        )
        doc = None if frontend is None else pickle.loads(frontend)
    if front_end is not None and (
        not isinstance(doc, dict) or not isinstance(doc.get("associator"), Associator)
    ):
        raise ValueError("not a front-end state")
    if isinstance(extra, PipelineState):
        localiser, robots = extra.localiser, extra.robots
    elif isinstance(extra, MapLocalisation):
        localiser, robots = _older_localiser(extra), robots_of(extra, doc)
    else:
        localiser, robots = PlaceLocaliser(seed), {}
    images = None
    if front_end is not None:
        assert doc is not None
        images = ImageFrontEnd(slam, front_end, robots=robots)
        images.set_associator(doc["associator"])
    return MapPipeline(slam, localiser=localiser, images=images, robots=robots)


def _older_localiser(loc: MapLocalisation) -> PlaceLocaliser:
    state: dict[str, Any] = vars(loc)
    out = PlaceLocaliser.__new__(PlaceLocaliser)
    out.localiser = state["localiser"]
    out.rng = state["rng"]
    out.appearance = state.get("appearance", AppearancePlaces())
    return out
