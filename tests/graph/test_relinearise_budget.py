"""A budget on the relative marginals one iSAM2 update relinearises
(SlamConfig.relinearise_budget): the variables past the threshold beyond it keep their
linearisation point until a later update, and the map gets there all the same."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np

from graph.config import SlamConfig
from graph.factors import is_landmark_key
from graph.isam import IncrementalGraph
from graph.slam import BearingSlam
from tests.graph._world import circle_frames

WINDOWED = SlamConfig(
    landmark_cap=12, pose_window=15, upkeep="budget_after_frame", relinearise_budget=None
)
"""A short window and a cap: many relative marginals (old poses', removed landmarks');
no budget."""


def _run(config: SlamConfig, frames: int = 150) -> BearingSlam:
    data, _, _ = circle_frames(frames, seed=4)
    slam = BearingSlam(config, rng=np.random.default_rng(0))
    for frame in data:
        slam.process(frame, with_covariance=False)
    return slam


def _jolt(graph: IncrementalGraph) -> None:
    """A firm prior 0.3 m off the newest pose, as a loop closure would pull it: the
    next relinearisation then meets most of the window's poses past the threshold."""
    theta = graph.linearization_point()
    newest = max(k for k in theta.keys() if not is_landmark_key(k))
    shifted = theta.atPose2(newest).compose(gtsam.Pose2(0.3, 0.0, 0.05))
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 0.01)
    graph.update([gtsam.PriorFactorPose2(newest, shifted, noise)])


def _moved(before: gtsam.Values, after: gtsam.Values) -> set[int]:
    out: set[int] = set()
    for k in before.keys():
        if is_landmark_key(k):
            same = np.array_equal(before.atPoint2(k), after.atPoint2(k))
        else:
            same = before.atPose2(k).equals(after.atPose2(k), 0.0)
        if not same:
            out.add(k)
    return out


def _estimate(graph: IncrementalGraph) -> dict[int, np.ndarray]:
    values = graph.estimate()
    return {
        k: np.asarray(values.atPoint2(k))
        if is_landmark_key(k)
        else np.array([values.atPose2(k).x(), values.atPose2(k).y()])
        for k in values.keys()
    }


def test_a_budget_that_never_binds_leaves_the_map_bit_for_bit() -> None:
    free = _run(WINDOWED)
    loose = _run(dataclasses.replace(WINDOWED, relinearise_budget=1_000_000))
    assert free.graph.marginals_touching(free.graph.linearization_point().keys()) > 20
    assert loose.graph.held_back_updates == 0
    np.testing.assert_array_equal(free.trajectory("r1")["r1"], loose.trajectory("r1")["r1"])


def _copy(slam: BearingSlam, config: SlamConfig) -> IncrementalGraph:
    """A graph of `config` holding `slam`'s factors, linearised where `slam`'s are."""
    graph = IncrementalGraph(config)
    factors = slam.graph.nonlinear_graph()
    graph.update([factors.at(i) for i in range(factors.size())], slam.graph.linearization_point())
    return graph


def test_a_relinearisation_takes_the_budget_and_leaves_the_rest_for_later() -> None:
    budget = 4
    slam = _run(WINDOWED)
    graph, free = (
        _copy(slam, dataclasses.replace(WINDOWED, relinearise_budget=budget)),
        _copy(slam, WINDOWED),
    )
    _jolt(graph)
    _jolt(free)
    held = graph.held_back_updates
    before = gtsam.Values(graph.linearization_point())
    graph.update()  # nothing new: the update's relinearisation, within the budget
    moved = _moved(before, graph.linearization_point())
    assert graph.held_back_updates == held + 1, "the jolt must exceed the budget"
    assert moved, "the farthest-moved variables are relinearised"
    largest = max(graph.marginals_touching([k]) for k in moved)
    assert graph.marginals_touching(moved) <= budget + largest
    assert len(moved) < len(_moved(before, _relinearised(free))), "the others wait"

    # Later updates take the rest, and the map ends where the unbudgeted one does.
    for _ in range(500):
        held = graph.held_back_updates
        graph.update()
        if graph.held_back_updates == held:
            break
    else:
        raise AssertionError("the held-back variables were never all relinearised")
    for _ in range(5):  # both to convergence: they took different paths there
        graph.relinearise()
        free.relinearise()
    mine, theirs = _estimate(graph), _estimate(free)
    worst = max(float(np.linalg.norm(mine[k] - theirs[k])) for k in mine)
    # Not the same steps, the same map: to within what the relinearisation threshold
    # leaves unrelinearised (either map's variables may sit that far from their point).
    assert 0.0 < worst < WINDOWED.relinearize_threshold, worst


def _relinearised(graph: IncrementalGraph) -> gtsam.Values:
    graph.relinearise()
    return graph.linearization_point()


def test_without_a_budget_the_upkeep_after_the_frame_makes_the_in_frame_map() -> None:
    """The default upkeep moves the removals after the frame's answer, not in the map."""
    base = dataclasses.replace(WINDOWED, relinearise_budget=None)
    inside = _run(dataclasses.replace(base, upkeep="in_frame"))
    after = _run(dataclasses.replace(base, upkeep="budget_after_frame"))
    after.settle()
    assert inside.removal_count > 5, "the run must exercise the budget"
    assert inside.removal_count == after.removal_count
    np.testing.assert_array_equal(inside.trajectory("r1")["r1"], after.trajectory("r1")["r1"])


def test_with_the_frame_doing_everything_the_budget_does_nothing() -> None:
    inside = _run(dataclasses.replace(WINDOWED, upkeep="in_frame", relinearise_budget=None))
    budgeted = _run(dataclasses.replace(WINDOWED, upkeep="in_frame", relinearise_budget=1))
    assert budgeted.graph.held_back_updates == 0
    np.testing.assert_array_equal(inside.trajectory("r1")["r1"], budgeted.trajectory("r1")["r1"])
