"""A tiny deterministic world for graph tests: a robot on a circle among landmarks."""

from __future__ import annotations

import math

import numpy as np

from graph.angles import wrap_angle
from graph.types import BearingObservation, FrameInput, Odometry, Pose2D


def circle_frames(
    n_frames: int,
    *,
    seed: int,
    n_landmarks: int = 40,
    radius: float = 5.0,
    step: float = 0.15,
    bearing_sigma: float = 0.01,
    max_range: float = 6.0,
    robot: str = "r1",
) -> tuple[list[FrameInput], np.ndarray, np.ndarray]:
    """Frames, true poses (n, 3) and landmark positions (M, 2) of a noisy circular run."""
    rng = np.random.default_rng(seed)
    angles = rng.uniform(-math.pi, math.pi, n_landmarks)
    radii = np.where(rng.random(n_landmarks) < 0.5, radius - 2.5, radius + 2.5)
    radii = radii + rng.uniform(-0.8, 0.8, n_landmarks)
    landmarks = np.column_stack([radii * np.cos(angles), radii * np.sin(angles)])
    dtheta = step / radius
    truth = np.zeros((n_frames, 3))
    frames: list[FrameInput] = []
    x, y, th = radius, 0.0, math.pi / 2
    for k in range(n_frames):
        if k > 0:
            x += step * math.cos(th + dtheta / 2)
            y += step * math.sin(th + dtheta / 2)
            th = wrap_angle(th + dtheta)
        truth[k] = (x, y, th)
        d = landmarks - (x, y)
        r = np.hypot(d[:, 0], d[:, 1])
        visible = np.flatnonzero((r < max_range) & (r > 0.5))
        obs = tuple(
            BearingObservation(
                wrap_angle(math.atan2(d[i, 1], d[i, 0]) - th + rng.normal(0, bearing_sigma)),
                str(i),
                bearing_sigma,
            )
            for i in visible
        )
        if k == 0:
            frames.append(FrameInput(robot, 0, 0.0, None, Pose2D(x, y, th), obs))
        else:
            odo = Odometry(
                step * math.cos(dtheta / 2) + rng.normal(0, 0.005),
                step * math.sin(dtheta / 2) + rng.normal(0, 0.005),
                dtheta + rng.normal(0, 0.002),
            )
            frames.append(FrameInput(robot, k, 0.1 * k, odo, None, obs))
    return frames, truth, landmarks
