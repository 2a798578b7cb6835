"""What GET /pose reports of a robot's localisation: its last frame result's, kept
across pickling (snapshots)."""

from __future__ import annotations

import pickle

import numpy as np

from graph.config import SlamConfig
from graph.slam import BearingSlam
from service.pipeline import FrameStep, MapPipeline
from service.pipeline.localiser import PlaceLocaliser
from tests.graph._world import circle_frames

FRAMES, _, _ = circle_frames(30, seed=2)


def _localised() -> tuple[MapPipeline, list[FrameStep]]:
    slam = BearingSlam(SlamConfig(landmark_cap=20), rng=np.random.default_rng(0))
    pipeline = MapPipeline(slam, localiser=PlaceLocaliser(seed=1))
    return pipeline, [pipeline.step(f) for f in FRAMES]


def test_localisation_is_what_the_last_frame_reported() -> None:
    pipeline, results = _localised()
    last = results[-1]
    assert pipeline.localiser is not None
    report = pipeline.localiser.localisation("r1", pipeline.robots["r1"])
    assert report == {"status": last.status, "place": last.place, "confidence": last.confidence}
    assert any(r.place is not None for r in results)  # places were learnt and matched
    localiser, robots = pickle.loads(pickle.dumps((pipeline.localiser, pipeline.robots)))
    assert localiser.localisation("r1", robots["r1"]) == report


def test_a_robot_without_a_frame_reports_no_place() -> None:
    pipeline, _ = _localised()
    assert pipeline.localiser is not None
    assert pipeline.localiser.localisation("r9", None) == {
        "status": "tracking",
        "place": None,
        "confidence": None,
    }
