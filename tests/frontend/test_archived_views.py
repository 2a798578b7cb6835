"""The associator's archive of views: a marginalised landmark keeps its descriptor views,
so a robot that does not know where it is can still recognise it (pose-free matching,
and association at its archived position), while the graph's own association, given
live landmarks only, never brings its label back."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest

from frontend.association import Association, Associator
from frontend.association_state import associator_from_doc, associator_to_doc
from frontend.features import Features
from tests.frontend.test_association import _features, _flip

BEARINGS_DEG = [-150.0, -90.0, -30.0, 30.0, 90.0, 150.0]
RANGE_M = 2.0


def _positions(pose: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> dict[str, np.ndarray]:
    """Landmark i at BEARINGS_DEG[i], RANGE_M from `pose` (map frame)."""
    x, y, th = pose
    return {
        f"L{i}": np.array(
            [
                x + RANGE_M * math.cos(th + math.radians(b)),
                y + RANGE_M * math.sin(th + math.radians(b)),
            ]
        )
        for i, b in enumerate(BEARINGS_DEG)
    }


def _seen_twice(assoc: Associator, feats: Features) -> Association:
    """The association of `feats` seen a second time from the origin (one frame committed
    before, no landmark live): every feature continues its track."""
    first = assoc.associate(
        feats, robot="r1", predicted_pose=(0, 0, 0), pose_cov=None, landmarks={}
    )
    assoc.commit(first, pose=(0, 0, 0), live_labels=())
    return assoc.associate(feats, robot="r1", predicted_pose=(0, 0, 0), pose_cov=None, landmarks={})


def _mapped(descs: np.ndarray) -> tuple[Associator, list[str]]:
    """An associator that learnt six landmarks from tracks (one robot at the origin) and
    the labels the graph gave them, all of them then marginalised."""
    assoc = Associator()
    feats = _features(BEARINGS_DEG, descs)
    again = _seen_twice(assoc, feats)
    labels = [o.label for o in sorted(again.observations, key=lambda o: o.bearing_rad)]
    assoc.commit(again, pose=(0, 0, 0), live_labels=set(labels))
    assert assoc.known_landmarks == len(BEARINGS_DEG)
    assoc.commit(
        assoc.associate(feats, robot="r1", predicted_pose=(0, 0, 0), pose_cov=None, landmarks={}),
        pose=(0, 0, 0),
        live_labels=(),
    )
    return assoc, labels


def test_an_archived_landmarks_views_still_let_a_place_be_recognised() -> None:
    rng = np.random.default_rng(3)
    descs = rng.integers(0, 256, (len(BEARINGS_DEG), 32), dtype=np.uint8)
    assoc, labels = _mapped(descs)
    assert assoc.known_landmarks == 0 and assoc.archived_landmarks == len(BEARINGS_DEG)
    assert assoc.has_views()

    # A robot elsewhere, turned by 40 deg, sees the same corners with a few bits changed.
    pose = (0.0, 0.0, math.radians(40.0))
    seen = _features([b - 40.0 for b in BEARINGS_DEG], np.stack([_flip(d, 4, rng) for d in descs]))
    obs, quality = assoc.match_without_pose(seen, labels)
    assert sorted(o.label for o in obs) == sorted(labels)
    assert np.all(quality > 0.5)
    by_label = {o.label: o.bearing_rad for o in obs}
    for label, b in zip(labels, BEARINGS_DEG, strict=True):
        assert math.isclose(by_label[label], math.radians(b - 40.0), abs_tol=1e-9)

    # Associated at their archived positions from the right pose (the relocalisation
    # check), they match; the graph's association, which is given live landmarks only,
    # matches nothing and the archive stays as it was.
    archived = {lb: (xy, None) for lb, xy in zip(labels, _positions().values(), strict=True)}
    cov = np.diag([1e-4, 1e-4, 1e-4])
    check = assoc.associate(seen, robot="r2", predicted_pose=pose, pose_cov=cov, landmarks=archived)
    assert sorted(check.landmark_matches) == sorted(labels)
    graph = assoc.associate(seen, robot="r2", predicted_pose=pose, pose_cov=cov, landmarks={})
    assert not graph.landmark_matches
    assoc.commit(graph, pose=pose, live_labels=())
    assert assoc.archived_landmarks == len(BEARINGS_DEG) and assoc.known_landmarks == 0


def test_a_landmark_removed_before_its_track_was_promoted_keeps_the_tracks_views() -> None:
    rng = np.random.default_rng(5)
    descs = rng.integers(0, 256, (2, 32), dtype=np.uint8)
    assoc = Associator()
    f = _features([30.0, -30.0], descs)
    r = _seen_twice(assoc, f)
    gone = r.observations[0].label
    # The estimator made the track a landmark and the cap removed it in the same frame.
    assoc.commit(r, pose=(0, 0, 0), live_labels=(), removed_labels={gone})
    assert assoc.archived_landmarks == 1 and assoc.known_landmarks == 0
    assert assoc.track_count("r1") == 2, "the track goes on as before"
    (views,) = assoc.views_of([gone])
    assert len(views) >= 1
    assert any(np.array_equal(v, descs[0]) or np.array_equal(v, descs[1]) for v in views)
    # Live again (restored by its label): its views come back from the archive.
    r = assoc.associate(f, robot="r1", predicted_pose=(0, 0, 0), pose_cov=None, landmarks={})
    assoc.commit(r, pose=(0, 0, 0), live_labels={gone})
    assert assoc.known_landmarks == 1 and assoc.archived_landmarks == 0


def test_the_archive_of_views_travels_in_the_state_document_and_in_old_pickles() -> None:
    rng = np.random.default_rng(8)
    descs = rng.integers(0, 256, (len(BEARINGS_DEG), 32), dtype=np.uint8)
    assoc, labels = _mapped(descs)
    doc = associator_to_doc(assoc)
    back = associator_from_doc(doc)
    assert back.archived_landmarks == len(labels)
    for a, b in zip(assoc.views_of(labels), back.views_of(labels), strict=True):
        assert np.array_equal(a, b)
    bad = {**doc, "archived": [{**doc["archived"][0], "label": ""}]}
    with pytest.raises(ValueError, match=r"associator\.archived\[0\]\.label"):
        associator_from_doc(bad)
    # A document from before the archive of views: accepted, with an empty archive.
    del doc["archived"]
    assert associator_from_doc(doc).archived_landmarks == 0
    # A pickled associator from then (a snapshot) loads with an empty archive.
    old = Associator()
    del old.__dict__["_archived"]
    loaded = pickle.loads(pickle.dumps(old))
    assert loaded.archived_landmarks == 0 and not loaded.has_views()
