"""The map pipeline's snapshot: taken and restored, the pipeline goes on as if it had
never stopped (up to iSAM2's rebuild); a snapshot in the layout older versions wrote
(the place localiser with per-map dicts of robot state, an OffGraphLog, pickled under
their old module names) loads into the same pipeline."""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest

from graph.config import SlamConfig
from graph.slam import BearingSlam
from graph.snapshot import capture
from graph.types import FrameInput
from service.pipeline import FrameStep, MapPipeline, appearance, legacy
from service.pipeline.localiser import PlaceLocaliser
from service.pipeline.snapshot import restore_pipeline, snapshot_pipeline
from tests.graph._world import circle_frames

MAPPER, _, _ = circle_frames(80, seed=3)
FOLLOWER = [
    dataclasses.replace(f, robot="b", initial_pose=None) for f in circle_frames(60, seed=3)[0]
]
"""The same circle again by a robot that starts without initial_pose (the localiser's
initialising and off-graph path)."""
FIRST, THEN = [*MAPPER[:60], *FOLLOWER[:30]], [*MAPPER[60:], *FOLLOWER[30:]]


def _pipeline() -> MapPipeline:
    slam = BearingSlam(SlamConfig(landmark_cap=25), rng=np.random.default_rng(0))
    pipeline = MapPipeline(slam, localiser=PlaceLocaliser(seed=0))
    for frame in FIRST:
        pipeline.step(frame)
    return pipeline


def _older_snapshot(pipeline: MapPipeline, monkeypatch: pytest.MonkeyPatch) -> bytes:
    """The pipeline's state as older versions pickled it."""
    for cls, module in (
        (legacy.MapLocalisation, "service.localisation"),
        (legacy.OffGraphLog, "service.offgraph"),
        (legacy.OffGraphFrame, "service.offgraph"),
        (legacy.AnchoredRun, "service.offgraph"),
        (appearance.AppearancePlaces, "service.appearance_places"),
    ):
        monkeypatch.setattr(cls, "__module__", module)
    robots, localiser = pipeline.robots, pipeline.localiser
    assert localiser is not None
    log = legacy.OffGraphLog()
    log.pending = {n: r.off_graph.pending for n, r in robots.items() if r.off_graph.pending}
    log.anchored = {n: r.off_graph.anchored for n, r in robots.items() if r.off_graph.anchored}
    log.settled = {n: r.off_graph.settled for n, r in robots.items() if r.off_graph.settled}
    log.reckoned = {
        n: r.off_graph.reckoned for n, r in robots.items() if r.off_graph.reckoned is not None
    }
    loc = legacy.MapLocalisation()
    vars(loc).update(
        localiser=localiser.localiser,
        rng=localiser.rng,
        appearance=localiser.appearance,
        last={n: r.last for n, r in robots.items() if r.last is not None},
        reported={n: r.reported for n, r in robots.items()},
        landmark_matches={},
        off_graph=log,
    )
    with legacy.older_names():
        return capture(pipeline.slam, extra=loc)


def _outcomes(pipeline: MapPipeline, frames: list[FrameInput]) -> list[tuple]:
    steps: list[FrameStep] = [pipeline.step(f) for f in frames]
    return [
        (s.robot, s.seq, s.status, s.place, (s.pose.x, s.pose.y, s.pose.theta), s.outcome is None)
        for s in steps
    ]


def test_a_restored_pipeline_goes_on_as_the_original(monkeypatch: pytest.MonkeyPatch) -> None:
    original = _pipeline()
    assert original.off_graph_count() > 0, "the follower had frames off the graph"
    blob, frontend = snapshot_pipeline(original)
    older = _older_snapshot(original, monkeypatch)
    monkeypatch.undo()
    restored = restore_pipeline(blob, frontend, seed=0)
    from_older = restore_pipeline(older, None, seed=0)
    assert "service.localisation" not in sys.modules  # the old names were put back
    for pipeline in (restored, from_older):
        assert pipeline.last_accepted() == original.last_accepted()
        assert pipeline.off_graph_count() == original.off_graph_count()
        assert pipeline.robots["b"].reported == original.robots["b"].reported
    expected, got = _outcomes(original, THEN), _outcomes(restored, THEN)
    # Bit for bit alike: the two snapshots hold the same state.
    assert _outcomes(from_older, THEN) == got
    # Alike up to iSAM2's rebuild at the snapshot's linearisation point (graph.snapshot).
    assert [(g[:4], g[5]) for g in got] == [(e[:4], e[5]) for e in expected]
    np.testing.assert_allclose([g[4] for g in got], [e[4] for e in expected], atol=1e-6)
