"""The bearing factors' robust loss (SlamConfig.bearing_loss)."""

from __future__ import annotations

import dataclasses
import math

import gtsam
import numpy as np
import pytest

from graph.angles import wrap_angle
from graph.config import SlamConfig
from graph.factors import bearing_noise
from graph.slam import BearingSlam
from graph.types import BearingObservation, FrameInput
from tests.graph._world import circle_frames

CFG = SlamConfig(
    landmark_cap=None,
    pose_window=40,
    window_observations=None,
    uncapped_window_observations=None,
    # The circle world's odometry is ~10x better than a wheeled robot's: say so (the
    # random walks of the default model would let Geman-McClure's non-convex loss wander).
    odometry_sigma_per_sqrt_metre=(0.0, 0.0, 0.0),
    odometry_sigma_per_sqrt_radian=0.0,
)
VICTIMS = 4
"""Landmarks of the ~15 in view that a look-alike takes over for 60 frames."""


@pytest.mark.parametrize(
    ("loss", "kernel"), [("huber", "Huber"), ("geman_mcclure", "GemanMcClure")]
)
def test_the_loss_is_gtsams_kernel_at_the_scale(loss: str, kernel: str) -> None:
    noise = bearing_noise(0.01, 1.2, loss)  # type: ignore[arg-type]
    assert isinstance(noise, gtsam.noiseModel.Robust)
    expected = getattr(gtsam.noiseModel.mEstimator, kernel).Create(1.2)
    assert type(noise.robust()).__name__ == kernel
    for e in (0.3, 1.0, 2.5, 9.0):
        assert noise.robust().weight(e) == pytest.approx(expected.weight(e))
    assert not isinstance(bearing_noise(0.01, None, loss), gtsam.noiseModel.Robust)  # type: ignore[arg-type]


def _with_look_alikes(
    frames: list[FrameInput], truth: np.ndarray, landmarks: np.ndarray, victims: int
) -> list[FrameInput]:
    """Frames 50-110: every observation of `victims` landmarks is of a point 0.6 m beside
    it (its corner hidden, a look-alike matched in its place), for as long as it is seen."""
    fakes = {str(i): landmarks[i] + (0.6, 0.0) for i in range(victims)}
    out = []
    for k, frame in enumerate(frames):
        if 50 <= k < 110:
            x, y, th = truth[k]
            obs = tuple(
                BearingObservation(
                    wrap_angle(math.atan2(fakes[o.label][1] - y, fakes[o.label][0] - x) - th),
                    o.label,
                    o.sigma_rad,
                )
                if o.label in fakes
                else o
                for o in frame.observations
            )
            frame = dataclasses.replace(frame, observations=obs)
        out.append(frame)
    return out


def _rmse(slam: BearingSlam, truth: np.ndarray) -> float:
    traj = slam.trajectory()["r1"]
    return float(np.sqrt(np.mean(np.sum((traj[:, 2:4] - truth[:, :2]) ** 2, axis=1))))


def test_geman_mcclure_shrugs_off_a_run_of_look_alike_matches_that_huber_follows() -> None:
    frames, truth, landmarks = circle_frames(160, seed=3, bearing_sigma=0.005)
    bad = _with_look_alikes(frames, truth, landmarks, VICTIMS)
    errors = {}
    for loss in ("huber", "geman_mcclure"):
        for name, run in (("clean", frames), ("bad", bad)):
            cfg = dataclasses.replace(CFG, bearing_loss=loss, huber_k=1.0)  # type: ignore[arg-type]
            slam = BearingSlam(cfg, rng=np.random.default_rng(0))
            for f in run:
                slam.process(f, with_covariance=False)
            errors[loss, name] = _rmse(slam, truth)
    # On clean data the two agree; the look-alike run hurts Huber's map more.
    assert errors["geman_mcclure", "clean"] < 1.2 * errors["huber", "clean"] + 0.005
    huber_harm = errors["huber", "bad"] - errors["huber", "clean"]
    gm_harm = errors["geman_mcclure", "bad"] - errors["geman_mcclure", "clean"]
    assert huber_harm > 0
    assert gm_harm < 0.5 * huber_harm, errors
