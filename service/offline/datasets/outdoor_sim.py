"""A deterministic outdoor world: a loop road through a park, trees 5-80 m from it.

The scale an indoor map's defaults do not cover: a robot drives a loop of a few
hundred metres and takes bearings (a panoramic camera, ~1 deg) to trees standing
between `min_clearance_m` and `max_clearance_m` from the road, up to `max_range_m`
away. Most trees are tens of metres off, so they are triangulated from long
baselines and their depth is uncertain: a map needs a larger depth range and
position-sigma threshold than a room's (see docs/configuration.md).

Convention: map frame x, y in metres, yaw theta in radians CCW from +x. The road is
a rounded rectangle `length_m` x `width_m` with its lower-left corner at the origin,
driven counter-clockwise from ``(corner_radius_m, 0)`` heading +x. A bearing is CCW
from the robot's forward axis, wrapped to (-pi, pi] (as service.offline.datasets.indoor_sim).

Everything random is drawn from the `rng` passed in: a seed gives the same world and
the same run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from graph.angles import wrap_angle, wrap_angles
from graph.types import BearingObservation, FrameInput, Odometry, Pose2D
from service.offline.datasets.indoor_sim import FloatArray, IntArray, SimRun, noisy_observations
from service.offline.evaluation import Trajectory

__all__ = [
    "CONFIGS",
    "OUTDOOR_TRIANGULATION",
    "OutdoorWorld",
    "make_outdoor_world",
    "outdoor_run",
    "simulate_outdoor",
]

_ROAD_SPACING_M = 0.25
"""Spacing of the road's sample points (tree clearances are measured to them)."""


@dataclass(frozen=True)
class OutdoorWorld:
    """A loop road and the trees around it.

    Attributes:
        length_m, width_m: outer size of the rounded-rectangle road, metres.
        corner_radius_m: radius of its four bends, metres.
        road: (K, 3) poses (x m, y m, theta rad) along the road every 0.25 m, from
            arc length 0 (``(corner_radius_m, 0)``, heading +x) counter-clockwise.
        landmarks: (M, 2) tree positions, metres.
        landmark_ids: (M,) distinct tree ids (observation labels are ``str(id)``).
        clearance_m: (M,) each tree's distance to the road, metres.
    """

    length_m: float
    width_m: float
    corner_radius_m: float
    road: FloatArray
    landmarks: FloatArray
    landmark_ids: IntArray
    clearance_m: FloatArray

    @property
    def loop_m(self) -> float:
        """Length of one lap, metres."""
        r = self.corner_radius_m
        return 2.0 * (self.length_m + self.width_m - 4.0 * r) + 2.0 * math.pi * r

    def road_pose(self, s_m: ArrayLike) -> FloatArray:
        """(N, 3) poses on the road at arc lengths (N,) metres (wrapped to one lap)."""
        r = self.corner_radius_m
        s = np.mod(np.asarray(s_m, dtype=np.float64), self.loop_m)
        out = np.empty((len(s), 3))
        start, theta0, offset = np.array([r, 0.0]), 0.0, 0.0
        for straight in (self.length_m - 2.0 * r, self.width_m - 2.0 * r) * 2:
            heading = np.array([math.cos(theta0), math.sin(theta0)])
            on = (s >= offset) & (s < offset + straight)
            out[on, :2] = start + (s[on] - offset)[:, None] * heading
            out[on, 2] = theta0
            start, offset = start + straight * heading, offset + straight
            # A left bend of radius r: theta grows with s by 1/r, a quarter turn.
            on = (s >= offset) & (s < offset + 0.5 * math.pi * r)
            theta = theta0 + (s[on] - offset) / r
            out[on, 0] = start[0] + r * (np.sin(theta) - math.sin(theta0))
            out[on, 1] = start[1] - r * (np.cos(theta) - math.cos(theta0))
            out[on, 2] = theta
            theta1 = theta0 + 0.5 * math.pi
            start = start + r * np.array(
                [math.sin(theta1) - math.sin(theta0), math.cos(theta0) - math.cos(theta1)]
            )
            theta0, offset = theta1, offset + 0.5 * math.pi * r
        out[:, 2] = wrap_angles(out[:, 2])
        return out

    def clearance(self, points_xy: FloatArray) -> FloatArray:
        """(N,) distance of (N, 2) points to the road, metres (to 0.13 m)."""
        p = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
        d2 = ((p[:, None, :] - self.road[None, :, :2]) ** 2).sum(axis=2)
        return np.sqrt(d2.min(axis=1))


def make_outdoor_world(
    *,
    rng: np.random.Generator,
    length_m: float = 160.0,
    width_m: float = 80.0,
    corner_radius_m: float = 20.0,
    trees: int = 150,
    min_clearance_m: float = 5.0,
    max_clearance_m: float = 80.0,
) -> OutdoorWorld:
    """Generate a loop road and `trees` trees whose distance to the road lies in
    [min_clearance_m, max_clearance_m]: a point of the road (uniform in arc length), a
    side, a distance uniform in that range along the road's normal; kept if no other
    part of the road comes nearer than min_clearance_m."""
    if not 0 < corner_radius_m <= 0.5 * min(length_m, width_m):
        raise ValueError("need 0 < corner_radius_m <= half the road's smaller side")
    if not 0 <= min_clearance_m < max_clearance_m:
        raise ValueError("need 0 <= min_clearance_m < max_clearance_m")
    if trees < 1:
        raise ValueError(f"trees must be >= 1, got {trees}")
    shape = OutdoorWorld(
        length_m=length_m,
        width_m=width_m,
        corner_radius_m=corner_radius_m,
        road=np.empty((0, 3)),
        landmarks=np.empty((0, 2)),
        landmark_ids=np.empty(0, dtype=np.int64),
        clearance_m=np.empty(0),
    )
    road = shape.road_pose(np.arange(0.0, shape.loop_m, _ROAD_SPACING_M))
    shape = OutdoorWorld(**{**shape.__dict__, "road": road})
    found = np.empty((0, 2))
    while len(found) < trees:
        n = 2 * trees
        at = shape.road_pose(rng.uniform(0.0, shape.loop_m, n))
        side = rng.choice([-1.0, 1.0], n)
        dist = rng.uniform(min_clearance_m, max_clearance_m, n)
        normal = np.column_stack([-np.sin(at[:, 2]), np.cos(at[:, 2])])
        cand = at[:, :2] + (side * dist)[:, None] * normal
        found = np.vstack([found, cand[shape.clearance(cand) >= min_clearance_m]])
    landmarks = found[:trees]
    return OutdoorWorld(
        **{
            **shape.__dict__,
            "landmarks": landmarks,
            "landmark_ids": np.arange(trees, dtype=np.int64),
            "clearance_m": shape.clearance(landmarks),
        }
    )


def simulate_outdoor(
    world: OutdoorWorld,
    *,
    laps: float = 1.5,
    rng: np.random.Generator,
    step_m: float = 0.75,
    frame_period_s: float = 0.5,
    odometry_noise: tuple[float, float, float] = (0.02, 0.02, 0.005),
    odometry_scale: float = 1.01,
    bearing_sigma_rad: float = math.radians(1.0),
    max_range_m: float = 100.0,
    max_observations: int = 12,
    robot: str = "r1",
) -> SimRun:
    """Drive `laps` laps of the road at `step_m` a frame and record the frames.

    Odometry (frames 1, 2, ...): the true motion (dx, dy, dtheta) in the previous robot
    frame, with dx, dy scaled by `odometry_scale` (a wheel-radius error: 1.01 reads 1 %
    too far) plus Gaussian noise of sigmas ``(kx d, ky d, kt d)`` for ``odometry_noise =
    (kx, ky, kt)`` (m/m, m/m, rad/m), d the distance travelled. No sigmas in the frames.

    Observations: of the trees within `max_range_m`, at most `max_observations` chosen
    at random each frame (a detector that finds some of the trees in view, far ones as
    often as near ones); bearing = truth + N(0, bearing_sigma_rad), wrapped; ``sigma`` =
    bearing_sigma_rad (None if 0); label = str(tree id).

    Stamps are ``seq * frame_period_s`` seconds; the first frame has the true pose as
    its `initial_pose` (so the map frame is the world's).
    """
    frames = round(laps * world.loop_m / step_m) + 1
    if frames < 2:
        raise ValueError("laps too short for one step")
    truth = world.road_pose(np.arange(frames) * step_m)
    kx, ky, kt = odometry_noise
    labels = [str(i) for i in world.landmark_ids.tolist()]

    def observe(pose: FloatArray) -> tuple[BearingObservation, ...]:
        rel = world.landmarks - pose[:2]
        in_range = np.flatnonzero(np.hypot(rel[:, 0], rel[:, 1]) <= max_range_m)
        seen = np.sort(rng.permutation(in_range)[:max_observations])
        return noisy_observations(
            rel[seen], float(pose[2]), [labels[i] for i in seen.tolist()], bearing_sigma_rad, rng
        )

    x0, y0, t0 = truth[0].tolist()
    out = [
        FrameInput(
            robot=robot,
            seq=0,
            stamp=0.0,
            initial_pose=Pose2D(x0, y0, t0),
            observations=observe(truth[0]),
        )
    ]
    for seq in range(1, frames):
        prev, cur = truth[seq - 1], truth[seq]
        c, s = math.cos(prev[2]), math.sin(prev[2])
        dxw, dyw = cur[0] - prev[0], cur[1] - prev[1]
        dx, dy = c * dxw + s * dyw, -s * dxw + c * dyw
        dtheta = wrap_angle(float(cur[2] - prev[2]))
        d = math.hypot(dx, dy)
        noise = rng.normal(0.0, 1.0, 3) * (kx * d, ky * d, kt * d)
        odo = Odometry(
            dx=odometry_scale * dx + float(noise[0]),
            dy=odometry_scale * dy + float(noise[1]),
            dtheta=wrap_angle(dtheta + float(noise[2])),
        )
        out.append(
            FrameInput(
                robot=robot,
                seq=seq,
                stamp=seq * frame_period_s,
                odometry=odo,
                observations=observe(cur),
            )
        )
    stamps = np.arange(frames, dtype=np.float64) * frame_period_s
    return SimRun(
        frames=out,
        ground_truth=Trajectory.from_poses(stamps, truth),
        landmarks=world.landmarks.copy(),
        landmark_ids=world.landmark_ids.copy(),
        world=world,
    )


OUTDOOR_TRIANGULATION: dict[str, Any] = {
    "max_depth_m": 100.0,
    "max_position_sigma_m": 2.0,
    "max_rays": 80,
}
"""The map config's triangulation group for an outdoor map: trees up to 100 m away, a
far tree's depth known to 2 m, and 80 rays kept (a long baseline for far trees)."""

CONFIGS: dict[str, dict[str, Any]] = {
    "default": {"landmark_cap": None},
    "outdoor": {"landmark_cap": None, "triangulation": OUTDOOR_TRIANGULATION},
    "depth_only": {"landmark_cap": None, "triangulation": {"max_depth_m": 100.0}},
    "outdoor_default_cap": {"triangulation": OUTDOOR_TRIANGULATION},
}
"""The maps the benchmark makes: the defaults, the outdoor triangulation, the depth range
alone, and the outdoor triangulation under the service's default landmark cap."""


def outdoor_run(seed: int, *, small: bool = False, odometry_scale: float = 1.01) -> SimRun:
    """The benchmark's run; `small`: a 120 x 60 m loop, 60 trees, 1.1 laps at 1 m a frame
    (369 frames, 8 bearings a frame) for tests."""
    if small:
        world = make_outdoor_world(
            rng=np.random.default_rng(seed),
            length_m=120.0,
            width_m=60.0,
            corner_radius_m=15.0,
            trees=60,
        )
        return simulate_outdoor(
            world,
            rng=np.random.default_rng(seed + 1),
            laps=1.1,
            step_m=1.0,
            max_observations=8,
            odometry_scale=odometry_scale,
        )
    return simulate_outdoor(
        make_outdoor_world(rng=np.random.default_rng(seed)),
        rng=np.random.default_rng(seed + 1),
        odometry_scale=odometry_scale,
    )
