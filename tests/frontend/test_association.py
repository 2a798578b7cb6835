"""Association on hand-built cases: look-alike landmarks, ratio test, tracks and labels."""

from __future__ import annotations

import math

import numpy as np

from frontend.association import AssociationConfig, Associator, _pairs_within
from frontend.features import Features
from graph.angles import wrap_angles


def _features(bearings_deg: list[float], descriptors: np.ndarray, v: float = 100.0) -> Features:
    n = len(bearings_deg)
    b = np.radians(np.asarray(bearings_deg, dtype=np.float64))
    return Features(
        u=np.zeros(n),
        v=np.full(n, v),
        bearing_rad=b,
        elevation_rad=np.zeros(n),
        sigma_rad=np.full(n, math.radians(0.2)),
        response=np.ones(n),
        octave=np.zeros(n, dtype=np.int64),
        descriptors=descriptors.astype(np.uint8),
        binary=True,
    )


def _flip(desc: np.ndarray, bits: int, rng: np.random.Generator) -> np.ndarray:
    """The descriptor with `bits` random bits flipped."""
    out = desc.copy()
    for i in rng.choice(256, bits, replace=False):
        out[i // 8] ^= np.uint8(1 << (i % 8))
    return out


def _learn(assoc: Associator, feats: Features, labels: dict[int, str]) -> None:
    """Make the associator know landmarks `labels` (feature index -> label) via tracks."""
    first = assoc.associate(
        feats, robot="r1", predicted_pose=(0, 0, 0), pose_cov=None, landmarks={}
    )
    assoc.commit(first, pose=(0, 0, 0), live_labels=())
    track_labels = sorted(t.label for t in assoc._tracks["r1"])
    # The graph turned the tracks of these features into landmarks with their labels.
    live = {track_labels[i] for i in labels}
    assoc.commit(
        assoc.associate(feats, robot="r1", predicted_pose=(0, 0, 0), pose_cov=None, landmarks={}),
        pose=(0, 0, 0),
        live_labels=live,
    )
    for i, name in labels.items():
        assert track_labels[i] in assoc._landmarks
        assoc._landmarks[name] = assoc._landmarks.pop(track_labels[i])


def test_lookalike_landmarks_are_told_apart_by_the_predicted_bearing() -> None:
    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, 32, dtype=np.uint8)
    # Two landmarks that look the same (descriptors 3 bits apart), 40° apart.
    descs = np.stack([base, _flip(base, 3, rng)])
    assoc = Associator()
    _learn(assoc, _features([0.0, 40.0], descs), {0: "A", 1: "B"})
    landmarks = {
        "A": (np.array([2.0, 0.0]), 0.01 * np.eye(2)),
        "B": (np.array([2.0 * math.cos(math.radians(40)), 2.0 * math.sin(math.radians(40))]), None),
    }
    # Seen again, each with a few more bits changed, in the other order.
    feats = _features([40.5, -0.4], np.stack([_flip(descs[1], 4, rng), _flip(descs[0], 4, rng)]))
    result = assoc.associate(
        feats,
        robot="r1",
        predicted_pose=(0.0, 0.0, 0.0),
        pose_cov=np.diag([1e-4, 1e-4, math.radians(1.0) ** 2]),
        landmarks=landmarks,
    )
    assert result.landmark_matches == {"A": 1, "B": 0}
    labels = {ob.label: ob.bearing_rad for ob in result.observations}
    assert labels["A"] == feats.bearing_rad[1] and labels["B"] == feats.bearing_rad[0]


def test_two_lookalikes_in_one_gate_give_no_match() -> None:
    rng = np.random.default_rng(1)
    base = rng.integers(0, 256, 32, dtype=np.uint8)
    assoc = Associator()
    _learn(assoc, _features([10.0], base[None, :]), {0: "A"})
    landmarks = {"A": (np.array([2.0 * math.cos(0.1745), 2.0 * math.sin(0.1745)]), None)}
    # Heading uncertain by 5°: both features (2° apart) fall in A's gate and look alike.
    feats = _features([9.0, 11.0], np.stack([_flip(base, 5, rng), _flip(base, 6, rng)]))
    result = assoc.associate(
        feats,
        robot="r1",
        predicted_pose=(0, 0, 0),
        pose_cov=np.diag([1e-4, 1e-4, math.radians(5.0) ** 2]),
        landmarks=landmarks,
    )
    assert result.landmark_matches == {}
    # One look-alike and one stranger: the look-alike is taken.
    feats = _features([9.0, 11.0], np.stack([_flip(base, 5, rng), rng.integers(0, 256, 32)]))
    result = assoc.associate(
        feats,
        robot="r1",
        predicted_pose=(0, 0, 0),
        pose_cov=np.diag([1e-4, 1e-4, math.radians(5.0) ** 2]),
        landmarks=landmarks,
    )
    assert result.landmark_matches == {"A": 0}


def test_a_landmark_outside_its_gate_is_not_matched() -> None:
    rng = np.random.default_rng(2)
    base = rng.integers(0, 256, 32, dtype=np.uint8)
    assoc = Associator()
    _learn(assoc, _features([0.0], base[None, :]), {0: "A"})
    feats = _features([25.0], base[None, :])  # identical look, 25° off a well-known pose
    result = assoc.associate(
        feats,
        robot="r1",
        predicted_pose=(0, 0, 0),
        pose_cov=np.diag([1e-4, 1e-4, 1e-4]),
        landmarks={"A": (np.array([3.0, 0.0]), None)},
    )
    assert result.landmark_matches == {}


def test_tracks_get_fresh_labels_are_reported_when_seen_twice_and_never_reused() -> None:
    rng = np.random.default_rng(3)
    descs = rng.integers(0, 256, (3, 32), dtype=np.uint8)
    cfg = AssociationConfig(track_min_length=2, report_when_trackless=False)
    assoc = Associator(cfg)
    seen_labels: set[str] = set()
    pose = np.zeros(3)
    frame0 = assoc.associate(
        _features([10.0, 100.0, -60.0], descs),
        robot="r1",
        predicted_pose=pose,
        pose_cov=None,
        landmarks={},
    )
    assert frame0.observations == ()  # first sighting: not reported yet
    assoc.commit(frame0, pose=pose, live_labels=())
    labels0 = {t.label for t in assoc._tracks["r1"]}
    assert len(labels0) == 3
    # The robot moves 0.1 m forward: the features move a little; all three are tracked.
    pose1 = np.array([0.1, 0.0, 0.0])
    frame1 = assoc.associate(
        _features([10.4, 100.1, -60.2], descs),
        robot="r1",
        predicted_pose=pose1,
        pose_cov=None,
        landmarks={},
    )
    assert {ob.label for ob in frame1.observations} == labels0
    assert set(frame1.kind) == {"track"}
    assoc.commit(frame1, pose=pose1, live_labels=())
    seen_labels |= labels0
    # The features disappear for longer than track_max_missed: tracks end.
    for _ in range(cfg.track_max_missed + 1):
        empty = assoc.associate(
            _features([], np.zeros((0, 32))),
            robot="r1",
            predicted_pose=pose1,
            pose_cov=None,
            landmarks={},
        )
        assoc.commit(empty, pose=pose1, live_labels=())
    assert assoc.track_count("r1") == 0
    # They come back: new tracks, new labels.
    again = assoc.associate(
        _features([10.4, 100.1, -60.2], descs),
        robot="r1",
        predicted_pose=pose1,
        pose_cov=None,
        landmarks={},
    )
    assoc.commit(again, pose=pose1, live_labels=())
    new_labels = {t.label for t in assoc._tracks["r1"]}
    assert len(new_labels) == 3 and not (new_labels & seen_labels)


def test_a_robot_without_tracks_reports_its_first_sightings_under_their_track_labels() -> None:
    rng = np.random.default_rng(5)
    descs = rng.integers(0, 256, (4, 32), dtype=np.uint8)
    assoc = Associator()  # track_min_length 2, report_when_trackless on
    pose = np.zeros(3)
    first = assoc.associate(
        _features([10.0, 100.0, -60.0], descs[:3]),
        robot="r1",
        predicted_pose=pose,
        pose_cov=None,
        landmarks={},
    )
    # The robot's first frame: every feature is reported, as a track, at once.
    assert len(first.observations) == 3 and set(first.kind) == {"track"}
    assoc.commit(first, pose=pose, live_labels=())
    labels0 = {t.label for t in assoc._tracks["r1"]}
    assert {ob.label for ob in first.observations} == labels0
    # Next frame: the same tracks again, under the same labels; a new feature starts a
    # track that is not reported yet (the robot has tracks now).
    pose1 = np.array([0.1, 0.0, 0.0])
    second = assoc.associate(
        _features([10.4, 100.1, -60.2, 160.0], descs),
        robot="r1",
        predicted_pose=pose1,
        pose_cov=None,
        landmarks={},
    )
    assert {ob.label for ob in second.observations} == labels0
    assoc.commit(second, pose=pose1, live_labels=())
    assert assoc.track_count("r1") == 4
    # Tracks dropped (a re-anchoring): the next frame reports its first sightings again.
    assoc.forget_tracks("r1")
    third = assoc.associate(
        _features([10.8, 100.2, -60.4, 160.1], descs),
        robot="r1",
        predicted_pose=pose1,
        pose_cov=None,
        landmarks={},
    )
    assert len(third.observations) == 4
    assert not ({ob.label for ob in third.observations} & (labels0 | {"t000003"}))


def test_a_new_track_label_stays_unique_when_another_association_was_committed_first() -> None:
    rng = np.random.default_rng(6)
    descs = rng.integers(0, 256, (2, 32), dtype=np.uint8)
    assoc = Associator()
    a = assoc.associate(
        _features([10.0], descs[:1]),
        robot="r1",
        predicted_pose=(0, 0, 0),
        pose_cov=None,
        landmarks={},
    )
    b = assoc.associate(
        _features([50.0], descs[1:]),
        robot="r2",
        predicted_pose=(0, 0, 0),
        pose_cov=None,
        landmarks={},
    )
    # Associated before either was committed: both were offered the same next label.
    assert a.observations[0].label == b.observations[0].label
    assoc.commit(a, pose=(0, 0, 0), live_labels=())
    assoc.commit(b, pose=(0, 0, 0), live_labels=())
    labels = [t.label for r in ("r1", "r2") for t in assoc._tracks[r]]
    assert len(set(labels)) == 2


def test_promoted_track_becomes_a_landmark_and_is_archived_when_marginalised() -> None:
    rng = np.random.default_rng(4)
    descs = rng.integers(0, 256, (2, 32), dtype=np.uint8)
    assoc = Associator()
    f = _features([30.0, -30.0], descs)
    r = assoc.associate(f, robot="r1", predicted_pose=(0, 0, 0), pose_cov=None, landmarks={})
    assoc.commit(r, pose=(0, 0, 0), live_labels=())
    r = assoc.associate(f, robot="r1", predicted_pose=(0, 0, 0), pose_cov=None, landmarks={})
    first = r.observations[0].label
    assoc.commit(r, pose=(0, 0, 0), live_labels={first})
    assert assoc.known_landmarks == 1 and assoc.track_count("r1") == 1
    # Next frame: the landmark is matched as a landmark, with its own label.
    xy = np.array([2.0 * math.cos(math.radians(30)), 2.0 * math.sin(math.radians(30))])
    if r.observations[0].bearing_rad < 0:
        xy[1] = -xy[1]
    r = assoc.associate(
        f,
        robot="r1",
        predicted_pose=(0, 0, 0),
        pose_cov=np.diag([1e-4, 1e-4, 1e-4]),
        landmarks={first: (xy, None)},
    )
    assert list(r.landmark_matches) == [first]
    # The graph marginalised it: its views move to the archive, out of the association.
    assoc.commit(r, pose=(0, 0, 0), live_labels=())
    assert assoc.known_landmarks == 0 and assoc.archived_landmarks == 1
    again = assoc.associate(
        f, robot="r1", predicted_pose=(0, 0, 0), pose_cov=np.diag([1e-4] * 3), landmarks={}
    )
    assert not again.landmark_matches


def test_at_most_one_observation_per_landmark_and_per_feature() -> None:
    rng = np.random.default_rng(5)
    base = rng.integers(0, 256, (6, 32), dtype=np.uint8)
    assoc = Associator()
    bearings = [0.0, 60.0, 120.0, 180.0, -120.0, -60.0]
    _learn(assoc, _features(bearings, base), {i: f"L{i}" for i in range(6)})
    landmarks = {
        f"L{i}": (np.array([3 * math.cos(math.radians(b)), 3 * math.sin(math.radians(b))]), None)
        for i, b in enumerate(bearings)
    }
    noisy = np.stack([_flip(d, 6, rng) for d in base] + [_flip(base[0], 6, rng)])
    feats = _features([*bearings, 0.3], noisy)
    result = assoc.associate(
        feats,
        robot="r1",
        predicted_pose=(0, 0, 0),
        pose_cov=np.diag([1e-4, 1e-4, 1e-4]),
        landmarks=landmarks,
    )
    labels = [ob.label for ob in result.observations if ob.label.startswith("L")]
    assert len(labels) == len(set(labels))
    assert len(set(result.feature_index.tolist())) == len(result.feature_index)
    # L0 has two look-alike candidates 0.3° apart: refused; the other five match.
    assert set(result.landmark_matches) == {f"L{i}" for i in range(1, 6)}


def test_a_well_matched_landmark_gets_a_tight_gate_against_a_lookalike_nearby() -> None:
    """Its lateral errors teach the associator the landmark's sigma (without covariances
    from the graph): a look-alike 3 deg off, the landmark's own corner missing, is then
    outside the gate; with the default 0.1 m sigma (gate ~5 deg at 2 m) it is taken."""
    rng = np.random.default_rng(4)
    base = rng.integers(0, 256, 32, dtype=np.uint8)
    lookalike = _flip(base, 6, rng)
    taken = {}
    for learn in (True, False):
        assoc = Associator(AssociationConfig(learn_landmark_sigma=learn))
        _learn(assoc, _features([0.0], base[None, :]), {0: "A"})
        landmarks = {"A": (np.array([2.0, 0.0]), None)}
        cov = np.diag([1e-6, 1e-6, math.radians(0.05) ** 2])
        for k in range(12):
            seen = _features([0.02 * (-1) ** k], _flip(base, 2, rng)[None, :])
            a = assoc.associate(
                seen, robot="r1", predicted_pose=(0, 0, 0), pose_cov=cov, landmarks=landmarks
            )
            assert a.landmark_matches == {"A": 0}
            assoc.commit(a, pose=(0, 0, 0), live_labels={"A"}, landmark_xy={"A": (2.0, 0.0)})
        fake = _features([3.0], lookalike[None, :])
        result = assoc.associate(
            fake, robot="r1", predicted_pose=(0, 0, 0), pose_cov=cov, landmarks=landmarks
        )
        taken[learn] = "A" in result.landmark_matches
    assert taken == {True: False, False: True}


def test_a_feature_a_landmark_could_have_been_starts_no_track() -> None:
    """Two near-identical features inside landmark A's gate: the ratio test takes
    neither, and neither becomes a new track (it would grow a second landmark on A's
    corner); a feature far from every landmark still starts one."""
    rng = np.random.default_rng(7)
    base = rng.integers(0, 256, 32, dtype=np.uint8)
    other = rng.integers(0, 256, 32, dtype=np.uint8)
    started = {}
    for rule in (True, False):
        assoc = Associator(AssociationConfig(no_tracks_from_contested=rule))
        _learn(assoc, _features([0.0], base[None, :]), {0: "A"})
        feats = _features(
            [-0.3, 0.3, 90.0], np.stack([_flip(base, 3, rng), _flip(base, 3, rng), other])
        )
        result = assoc.associate(
            feats,
            robot="r2",
            predicted_pose=(0, 0, 0),
            pose_cov=np.diag([1e-4, 1e-4, math.radians(1.0) ** 2]),
            landmarks={"A": (np.array([2.0, 0.0]), None)},
        )
        assert result.landmark_matches == {}
        started[rule] = sorted(result.unmatched.tolist())
    assert started == {True: [2], False: [0, 1, 2]}


def test_pairs_within_equals_the_full_gate_test_across_the_seam() -> None:
    """The bisection over sorted bearings finds exactly the pairs a full (L, N) test
    finds, in np.nonzero's order, also for bearings on both sides of +-pi."""
    rng = np.random.default_rng(11)
    for _ in range(20):
        predicted = wrap_angles(rng.uniform(-np.pi, np.pi, 40))
        bearings = wrap_angles(
            np.concatenate([rng.uniform(-np.pi, np.pi, 300), [np.pi, -np.pi + 1e-12, 3.14]])
        )
        half = np.radians(5.0)
        li, fi = _pairs_within(predicted, bearings, half)
        full = np.abs(wrap_angles(bearings[None, :] - predicted[:, None])) <= half
        want_l, want_f = np.nonzero(full)
        exact = np.abs(wrap_angles(bearings[fi] - predicted[li])) <= half
        np.testing.assert_array_equal(li[exact], want_l)
        np.testing.assert_array_equal(fi[exact], want_f)
        assert len(want_l) > 0


def test_a_feature_at_a_matched_landmarks_bearing_starts_no_track() -> None:
    """The top and bottom corner of a vertical edge have one bearing: once one of them is a
    landmark, the other starts no track (it would become a second landmark on the same
    2-D point, taking a second place under the cap); one 1 deg away does."""
    rng = np.random.default_rng(7)
    descs = rng.integers(0, 256, (3, 32), dtype=np.uint8)
    on = Associator(AssociationConfig())  # the default: 0.3 deg
    off = Associator(AssociationConfig(coincident_rad=0.0))
    for assoc in (on, off):
        _learn(assoc, _features([10.0], descs[:1]), {0: "A"})
    landmarks = {"A": (np.array([2.0 * math.cos(0.1745), 2.0 * math.sin(0.1745)]), None)}
    # A seen again; 0.1 deg along, a stranger (the edge's other end); 1 deg along, another.
    feats = _features([10.0, 10.1, 11.0], descs)
    with_rule = on.associate(
        feats, robot="r1", predicted_pose=(0, 0, 0), pose_cov=None, landmarks=landmarks
    )
    without = off.associate(
        feats, robot="r1", predicted_pose=(0, 0, 0), pose_cov=None, landmarks=landmarks
    )
    assert with_rule.landmark_matches == without.landmark_matches == {"A": 0}
    assert without.unmatched.tolist() == [1, 2]
    assert with_rule.unmatched.tolist() == [2]


def test_a_landmark_with_a_known_height_takes_only_features_at_its_elevation() -> None:
    """A look-alike at the landmark's bearing but 2.2 deg above the elevation its learnt
    height predicts (a corner of another poster on a farther wall, seen through a door) is
    not taken with the default gate; one 0.8 deg off is. The old gate (2 tolerances)
    took both."""
    rng = np.random.default_rng(11)
    desc = rng.integers(0, 256, (1, 32), dtype=np.uint8)
    predicted_deg = math.degrees(math.atan2(0.5, 2.0))  # 0.5 m above the camera, 2 m away

    default_gate = AssociationConfig().landmark_elevation_gate

    def taken(offset_deg: float, gate: float = default_gate) -> dict[str, int]:
        assoc = Associator(AssociationConfig(landmark_elevation_gate=gate))
        _learn(assoc, _features([0.0], desc), {0: "A"})
        assoc._landmarks["A"].height_m = 0.5
        feats = _features([0.0], desc)
        feats.elevation_rad[:] = math.radians(predicted_deg + offset_deg)
        return assoc.associate(
            feats,
            robot="r1",
            predicted_pose=(0, 0, 0),
            pose_cov=None,
            landmarks={"A": (np.array([2.0, 0.0]), None)},
        ).landmark_matches

    assert taken(0.8) == {"A": 0}
    assert taken(2.2) == {}
    assert taken(2.2, 2.0) == {"A": 0}
