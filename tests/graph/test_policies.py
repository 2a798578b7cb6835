"""Landmark-selection policies: the paper's coverage reasoning, baselines, registry."""

from __future__ import annotations

import json

import numpy as np
import pytest

from graph.policies import (
    POLICY_NAMES,
    LandmarkTable,
    Removal,
    coverage_clusters,
    get_policy,
    information_content,
)


def _table(
    observed_from: list[list[float]] | np.ndarray,
    information: list[float] | np.ndarray | None = None,
    *,
    ids: list[int] | None = None,
    counts: list[int] | None = None,
    first_seen: list[int] | None = None,
) -> LandmarkTable:
    n = len(observed_from)
    return LandmarkTable(
        ids=np.asarray(ids if ids is not None else np.arange(100, 100 + n)),
        observed_from=np.asarray(observed_from, dtype=np.float64),
        counts=np.asarray(counts if counts is not None else np.full(n, 5)),
        first_seen=np.asarray(first_seen if first_seen is not None else np.arange(n)),
        information=None if information is None else np.asarray(information, dtype=np.float64),
    )


def _two_rooms() -> LandmarkTable:
    """Room 1 (x in [0, 5] m): 12 precise landmarks seen from all over the room.

    Room 2 (x in [10, 15] m): 3 uncertain landmarks seen from its middle.
    Ids 100-111 are in room 1, 112-114 in room 2.
    """
    grid = np.array([[x, y] for x in (0.5, 2.5, 4.5) for y in (0.5, 1.8, 3.2, 4.5)])
    room1_info = [310.0, 120.0, 400.0, 75.0, 260.0, 50.0, 180.0, 355.0, 90.0, 220.0, 140.0, 60.0]
    room2 = [[12.0, 2.0], [13.0, 2.5], [12.5, 3.2]]
    room2_info = [3.0, 1.0, 5.0]
    return _table(np.vstack([grid, room2]), room1_info + room2_info)


def test_information_content_on_known_covariances() -> None:
    cov = np.array(
        [
            [[0.01, 0.0], [0.0, 0.04]],  # 100 + 25
            [[4.0, 1.5], [1.5, 0.5]],  # 0.25 + 2 (off-diagonal terms ignored, eq. 3-4)
            [[1.0, 0.0], [0.0, 1.0]],
        ]
    )
    np.testing.assert_allclose(information_content(cov), [125.0, 2.25, 2.0])


@pytest.mark.parametrize(
    "cov", [np.eye(2), np.zeros((1, 2, 2)), np.array([[[1.0, 0.0], [0.0, -1.0]]])]
)
def test_information_content_refuses_bad_covariances(cov: np.ndarray) -> None:
    with pytest.raises(ValueError):
        information_content(cov)


def test_coverage_clusters_shapes_and_spreads() -> None:
    table = _two_rooms()
    clusters = coverage_clusters(table, rng=np.random.default_rng(0))
    assert clusters.k == 4  # ceil(15 / 4)
    assert clusters.labels.shape == (15,)
    assert clusters.centres.shape == (4, 2)
    assert clusters.spreads.shape == (4,)
    assert clusters.sizes.sum() == 15
    assert table.information is not None
    for c in range(clusters.k):
        info = table.information[clusters.labels == c]
        assert clusters.spreads[c] == pytest.approx(info.max() - info.min())
    room2 = set(clusters.labels[12:].tolist())
    assert len(room2) == 1
    assert room2.isdisjoint(clusters.labels[:12].tolist())  # the rooms are not mixed


@pytest.mark.parametrize("seed", range(25))
def test_coverage_protects_the_poorly_covered_room_information_does_not(seed: int) -> None:
    table = _two_rooms()
    assert table.information is not None
    coverage = get_policy("coverage_paper").select(table, rng=np.random.default_rng(seed))
    information = get_policy("information").select(table, rng=np.random.default_rng(seed))

    assert information.landmark_id == 113  # the least precise landmark, in room 2
    assert 100 <= coverage.landmark_id <= 111  # coverage takes one from room 1 instead

    clusters = coverage_clusters(table, rng=np.random.default_rng(seed))
    widest = int(np.argmax(clusters.spreads))
    members = np.flatnonzero(clusters.labels == widest)
    expected = table.ids[members[np.argmin(table.information[members])]]
    assert coverage.landmark_id == expected
    assert coverage.details["cluster"] == widest
    assert coverage.details["cluster_spread"] == pytest.approx(clusters.spreads.max())
    assert sorted(coverage.details["cluster_members"]) == sorted(table.ids[members].tolist())
    assert coverage.details["information"] == pytest.approx(table.information[members].min())


def test_a_singleton_cluster_is_never_chosen_while_a_larger_one_exists() -> None:
    # four equally precise landmarks seen from one spot (spread 0) and one lone,
    # very uncertain landmark far away: the lone one is all the coverage there is
    observed = [[0.0, 0.0], [0.1, 0.0], [0.0, 0.1], [0.1, 0.1], [30.0, 30.0]]
    table = _table(observed, [100.0, 100.0, 100.0, 100.0, 0.5])
    for seed in range(10):
        removal = get_policy("coverage_paper").select(table, rng=np.random.default_rng(seed))
        assert removal.landmark_id == 100  # all spreads 0: the larger cluster, lowest id
        assert removal.details["spreads"] == [0.0, 0.0]
    assert get_policy("information").select(table, rng=np.random.default_rng(0)).landmark_id == 104


@pytest.mark.parametrize("seed", range(10))
def test_coverage_keeps_a_lone_landmark_and_takes_the_least_informative_shared_one(
    seed: int,
) -> None:
    # Two rooms of four (x=0 and x=50) and a lone landmark far away, known as well as the
    # median. The paper's rule takes the lowest I of the widest-spread cluster (the one
    # holding the best landmark, I=1000); the product's takes the lowest I of all but the
    # protected lone one.
    room = [[0.0, 0.0], [0.0, 1.0], [1.0, 0.0], [1.0, 1.0]]
    observed = [*room, *([x + 50.0, y] for x, y in room), [200.0, 200.0]]  # k = 3
    info = [1000.0, 50.0, 60.0, 70.0, 10.0, 20.0, 30.0, 40.0, 45.0]  # median 45
    table = _table(observed, info, ids=list(range(1, 10)))
    rng = np.random.default_rng(seed)
    removal = get_policy("coverage").select(table, rng=rng)
    assert removal.landmark_id == 5
    assert removal.details["protected"] == [9]
    assert sorted(removal.details["cluster_members"]) == [5, 6, 7, 8]
    paper = get_policy("coverage_paper").select(table, rng=np.random.default_rng(seed))
    assert paper.landmark_id == 2
    assert get_policy("information").select(table, rng=rng).landmark_id == 5


@pytest.mark.parametrize("seed", range(5))
def test_coverage_does_not_protect_a_lone_landmark_known_worse_than_the_median(
    seed: int,
) -> None:
    # The same rooms, the lone landmark barely known (a landmark just triangulated from a
    # new place): it covers its region with an uncertain position and is not protected.
    room = [[0.0, 0.0], [0.0, 1.0], [1.0, 0.0], [1.0, 1.0]]
    observed = [*room, *([x + 50.0, y] for x, y in room), [200.0, 200.0]]
    info = [1000.0, 50.0, 60.0, 70.0, 10.0, 20.0, 30.0, 40.0, 1.0]
    table = _table(observed, info, ids=list(range(1, 10)))
    removal = get_policy("coverage").select(table, rng=np.random.default_rng(seed))
    assert removal.landmark_id == 9
    assert removal.details["protected"] == []


def test_coverage_with_only_lone_landmarks_removes_the_least_informative() -> None:
    table = _table([[0.0, 0.0], [90.0, 0.0]], [5.0, 2.0], ids=[1, 2])
    removal = get_policy("coverage").select(table, rng=np.random.default_rng(0))
    assert removal.landmark_id == 2


def test_coverage_ties_prefer_the_larger_cluster_then_lowest_information_then_id() -> None:
    # cluster at x=0: three landmarks with spread 10; cluster at x=50: two with spread 10
    observed = [[50.0, 0.0], [50.0, 1.0], [0.0, 0.0], [0.0, 1.0], [1.0, 0.0]]
    table = _table(observed, [5.0, 15.0, 30.0, 20.0, 20.0], ids=[7, 3, 9, 8, 2])
    removal = get_policy("coverage_paper").select(table, rng=np.random.default_rng(0))
    assert removal.landmark_id == 2  # larger cluster; I = 20 twice, lowest id
    assert removal.details["cluster_spread"] == pytest.approx(10.0)


def test_coverage_with_only_singletons_removes_the_lowest_information() -> None:
    table = _table([[1.0, 2.0]], [42.0])
    removal = get_policy("coverage_paper").select(table, rng=np.random.default_rng(0))
    assert removal.landmark_id == 100
    assert "single landmark" in removal.reason


def test_coverage_reason_names_cluster_spread_and_information() -> None:
    table = _two_rooms()
    removal = get_policy("coverage_paper").select(table, rng=np.random.default_rng(0))
    d = removal.details
    assert removal.policy == "coverage_paper"
    assert f"cluster {d['cluster']}" in removal.reason
    assert f"D={d['cluster_spread']:.4g}" in removal.reason
    assert f"{d['information']:.4g} 1/m²" in removal.reason
    assert f"of {d['k']}" in removal.reason


@pytest.mark.parametrize("name", POLICY_NAMES)
def test_details_are_json_serialisable(name: str) -> None:
    removal = get_policy(name).select(_two_rooms(), rng=np.random.default_rng(0))
    assert isinstance(removal, Removal)
    assert type(removal.landmark_id) is int
    assert json.loads(json.dumps(removal.details)) == removal.details
    assert removal.policy == name
    assert removal.reason


def _small_table(information: list[float] | None = None) -> LandmarkTable:
    return _table(
        [[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0], [4.0, 0.0]],
        information,
        ids=[10, 11, 12, 13, 14],
        counts=[9, 2, 2, 7, 3],
        first_seen=[4, 6, 5, 1, 1],
    )


def test_information_picks_lowest_information_ties_by_id() -> None:
    table = _small_table([8.0, 3.0, 9.0, 3.0, 4.0])
    removal = get_policy("information").select(table, rng=np.random.default_rng(0))
    assert removal.landmark_id == 11
    assert removal.details["information"] == 3.0


def test_oldest_picks_smallest_first_seen_ties_by_id() -> None:
    removal = get_policy("oldest").select(_small_table(), rng=np.random.default_rng(0))
    assert removal.landmark_id == 13  # frames 1 and 1: ids 13 and 14
    assert removal.details["first_seen"] == 1


def test_least_observed_picks_fewest_observations_ties_by_age_then_id() -> None:
    removal = get_policy("least_observed").select(_small_table(), rng=np.random.default_rng(0))
    assert removal.landmark_id == 12  # counts 2 and 2: 12 was added at frame 5, 11 at 6
    table = _table([[0.0, 0.0]] * 3, ids=[5, 4, 6], counts=[1, 1, 1], first_seen=[2, 2, 2])
    assert get_policy("least_observed").select(table, rng=np.random.default_rng(0)).landmark_id == 4


def test_random_is_reproducible_from_a_seed_and_uniform() -> None:
    table = _small_table()
    policy = get_policy("random")
    first = [policy.select(table, rng=np.random.default_rng(s)).landmark_id for s in range(50)]
    again = [policy.select(table, rng=np.random.default_rng(s)).landmark_id for s in range(50)]
    assert first == again
    rng = np.random.default_rng(123)
    draws = [policy.select(table, rng=rng).landmark_id for _ in range(5000)]
    freq = np.bincount(np.asarray(draws) - 10, minlength=5) / 5000
    np.testing.assert_allclose(freq, 0.2, atol=0.03)


def test_registry_lookup() -> None:
    assert POLICY_NAMES == (
        "coverage",
        "coverage_paper",
        "information",
        "oldest",
        "least_observed",
        "random",
    )
    for name in POLICY_NAMES:
        policy = get_policy(name)
        assert policy.name == name
    assert get_policy("coverage").needs_information
    assert get_policy("coverage_paper").needs_information
    assert get_policy("information").needs_information
    assert not get_policy("oldest").needs_information
    assert not get_policy("least_observed").needs_information
    assert not get_policy("random").needs_information


def test_unknown_policy_lists_the_known_names() -> None:
    with pytest.raises(ValueError, match="unknown landmark policy 'newest'") as err:
        get_policy("newest")
    for name in POLICY_NAMES:
        assert name in str(err.value)


@pytest.mark.parametrize("name", POLICY_NAMES)
def test_empty_table_is_refused(name: str) -> None:
    empty = _table(np.zeros((0, 2)), [])
    with pytest.raises(ValueError, match="no live landmarks"):
        get_policy(name).select(empty, rng=np.random.default_rng(0))


@pytest.mark.parametrize("name", [n for n in POLICY_NAMES if get_policy(n).needs_information])
def test_missing_information_is_refused(name: str) -> None:
    with pytest.raises(ValueError, match="needs the landmarks' information"):
        get_policy(name).select(_small_table(), rng=np.random.default_rng(0))


@pytest.mark.parametrize("name", [n for n in POLICY_NAMES if not get_policy(n).needs_information])
def test_policies_without_information_accept_a_table_without_it(name: str) -> None:
    removal = get_policy(name).select(_small_table(), rng=np.random.default_rng(0))
    assert removal.landmark_id in {10, 11, 12, 13, 14}


def test_table_refuses_inconsistent_rows_and_duplicate_ids() -> None:
    with pytest.raises(ValueError, match="same landmarks"):
        _table([[0.0, 0.0], [1.0, 1.0]], counts=[1])
    with pytest.raises(ValueError, match="unique"):
        _table([[0.0, 0.0], [1.0, 1.0]], ids=[3, 3])
    with pytest.raises(ValueError, match="information has 1 values"):
        _table([[0.0, 0.0], [1.0, 1.0]], [1.0])
    with pytest.raises(ValueError, match="finite"):
        _table([[0.0, 0.0], [1.0, 1.0]], [1.0, np.nan])
