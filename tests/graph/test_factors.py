"""Factor construction: bearing factors share their noise model (graph.factors)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from graph.config import BearingLoss, SlamConfig
from graph.factors import bearing_factor, bearing_noise, landmark_key, pose_key
from graph.slam import BearingSlam
from tests.graph._world import circle_frames

BOUNDED = SlamConfig(landmark_cap=8, pose_window=15, window_observations=None, max_keyframes=6)


@pytest.mark.parametrize("huber_k", [None, 1.345])
@pytest.mark.parametrize("loss", ["huber", "geman_mcclure"])
def test_a_shared_noise_model_gives_the_error_and_jacobian_of_a_model_of_its_own(
    huber_k: float | None, loss: BearingLoss
) -> None:
    rng = np.random.default_rng(3)
    x, lm = pose_key(0, 1), landmark_key(4)
    shared = bearing_factor(x, lm, 0.3, 0.02, huber_k, loss)
    assert shared.noiseModel() is bearing_noise(0.02, huber_k, loss)
    base: gtsam.noiseModel.Base = gtsam.noiseModel.Isotropic.Sigma(1, 0.02)
    if huber_k is not None:
        est = gtsam.noiseModel.mEstimator
        kernel = est.Huber if loss == "huber" else est.GemanMcClure
        base = gtsam.noiseModel.Robust.Create(kernel.Create(huber_k), base)
    own = gtsam.BearingFactor2D(x, lm, gtsam.Rot2(0.3), base)
    for _ in range(20):
        values = gtsam.Values()
        values.insert(x, gtsam.Pose2(*rng.normal(0.0, 1.0, 3)))
        values.insert(lm, rng.normal(0.0, 3.0, 2))
        assert shared.error(values) == own.error(values)
        a, b = shared.linearize(values), own.linearize(values)
        assert np.array_equal(a.augmentedJacobian(), b.augmentedJacobian())


def test_a_lifelong_map_holds_one_bearing_noise_model_however_many_frames() -> None:
    """A bearing factor carries no model of its own (~0.4 KiB of heap each): the graph's
    bearing factors, thousands in a dense lifelong window, all point to one model."""
    frames, _, _ = circle_frames(600, seed=11, n_landmarks=30)
    slam = BearingSlam(BOUNDED, rng=np.random.default_rng(4))
    seen: list[tuple[int, int]] = []
    for i, f in enumerate(frames, start=1):
        slam.process(f, with_covariance=False)
        if i % 150 == 0:
            graph = slam.graph.nonlinear_graph()
            bearings = [
                factor
                for j in range(graph.size())
                if isinstance(factor := graph.at(j), gtsam.BearingFactor2D)
            ]
            models = [b.noiseModel() for b in bearings]  # held: ids stay distinct
            seen.append((len(bearings), len({id(m) for m in models})))
    assert slam.removal_count > 0, "the run must remove landmarks"
    assert max(count for count, _ in seen) > 50, seen
    assert all(models == 1 for _, models in seen), seen
