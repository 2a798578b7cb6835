"""MapLocalisation.localisation(robot): what GET /pose reports, kept across pickling
(snapshots), including snapshots written before it was recorded."""

from __future__ import annotations

import pickle

import numpy as np

from graph.config import SlamConfig
from graph.slam import BearingSlam
from service.localisation import MapLocalisation
from tests.graph._world import circle_frames

FRAMES, _, _ = circle_frames(30, seed=2)


def _localised() -> tuple[MapLocalisation, list]:
    slam = BearingSlam(SlamConfig(landmark_cap=20), rng=np.random.default_rng(0))
    loc = MapLocalisation(seed=1)
    return loc, [loc.process(slam, f) for f in FRAMES]


def test_localisation_is_what_the_last_frame_reported() -> None:
    loc, results = _localised()
    last = results[-1]
    assert loc.localisation("r1") == {
        "status": last.status,
        "place": last.place,
        "confidence": last.confidence,
    }
    assert any(r.place is not None for r in results)  # places were learnt and matched
    again = pickle.loads(pickle.dumps(loc))
    assert again.localisation("r1") == loc.localisation("r1")


def test_a_snapshot_from_before_the_report_field_loads() -> None:
    loc, results = _localised()
    state = dict(loc.__dict__)
    del state["reported"]
    old = MapLocalisation.__new__(MapLocalisation)
    old.__setstate__(state)
    assert old.localisation("r1") == {
        "status": results[-1].status,
        "place": None,
        "confidence": None,
    }
