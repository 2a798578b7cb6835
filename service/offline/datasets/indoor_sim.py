"""A deterministic indoor world: rooms joined by doors, landmarks seen only from their room.

The situation of Hochdorfer & Schlegel's Fig. 1: a grid of square rooms, a door
(a gap in the wall) between every two neighbouring rooms, landmarks near the
walls inside each room. A robot wanders from waypoint to waypoint, now and then
through a door into a neighbouring room, so it revisits rooms many times (loop
closures). It sees the landmarks of the room it is in, within a range.

Convention: map frame x, y in metres, yaw theta in radians CCW from +x. Room
``iy * nx + ix`` covers ``[ix S, (ix + 1) S) x [iy S, (iy + 1) S)`` for room size
S; room 0 is at the origin. A bearing is CCW from the robot's forward axis,
wrapped to (-pi, pi]: a landmark straight ahead is at 0, one to the left at +pi/2.

Everything random is drawn from the `rng` passed in: a seed gives the same
world and the same run.
"""

from __future__ import annotations

import math
import os
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graph.angles import wrap_angle, wrap_angles
from graph.types import BearingObservation, FrameInput, Odometry, Pose2D
from service.offline.evaluation import Trajectory, write_tum
from service.offline.frame_files import write_frames

if TYPE_CHECKING:
    from service.offline.datasets.outdoor_sim import OutdoorWorld

__all__ = [
    "DENSE_OBSERVATIONS",
    "IndoorWorld",
    "SimRun",
    "bearings_from_pose",
    "make_world",
    "noisy_observations",
    "simulate",
    "write_run",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

_WALL_OFFSET_M = 0.05

DENSE_OBSERVATIONS: dict[str, Any] = {"max_observations": 30, "max_range_m": 6.0}
"""`simulate` arguments of the dense world: every landmark of the robot's room within
6 m, up to 30. In the default 3x3 rooms with 225 landmarks (25 a room) a frame holds
~25 labelled bearings (the default `simulate`: ~10), as a camera front end gives."""
"""Landmarks stand at least this far inside their room's walls."""


@dataclass(frozen=True)
class IndoorWorld:
    """A grid of rooms with doors and landmarks.

    Attributes:
        rooms: (nx, ny) rooms along x and y.
        room_size_m: side S of each square room.
        door_width_m: width of each door gap.
        drive_margin_m: the robot keeps this far from walls, except when it
            passes a door (straight through the door centre, along its normal).
        doors: (D, 2) door centres on the shared walls, metres.
        door_rooms: (D, 2) the two rooms each door joins.
        landmarks: (M, 2) landmark positions, metres.
        landmark_ids: (M,) distinct landmark ids.
        landmark_rooms: (M,) room of each landmark.
    """

    rooms: tuple[int, int]
    room_size_m: float
    door_width_m: float
    drive_margin_m: float
    doors: FloatArray
    door_rooms: IntArray
    landmarks: FloatArray
    landmark_ids: IntArray
    landmark_rooms: IntArray

    @property
    def n_rooms(self) -> int:
        return self.rooms[0] * self.rooms[1]

    def room_of(self, xy: ArrayLike) -> IntArray:
        """(N,) room index of each of (N, 2) points; -1 outside the grid."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        cell = np.floor(p / self.room_size_m).astype(np.int64)
        nx, ny = self.rooms
        inside = (cell[:, 0] >= 0) & (cell[:, 0] < nx) & (cell[:, 1] >= 0) & (cell[:, 1] < ny)
        return np.where(inside, cell[:, 1] * nx + cell[:, 0], -1)

    def room_origin(self, room: int) -> FloatArray:
        """(2,) lower-left corner of a room, metres."""
        nx = self.rooms[0]
        return np.array([room % nx, room // nx], dtype=np.float64) * self.room_size_m

    def room_centre(self, room: int) -> FloatArray:
        """(2,) centre of a room, metres."""
        return self.room_origin(room) + 0.5 * self.room_size_m

    def neighbours(self, room: int) -> list[tuple[int, int]]:
        """(door index, neighbouring room) for each door of a room."""
        out = []
        for d, (a, b) in enumerate(self.door_rooms):
            if a == room:
                out.append((d, int(b)))
            elif b == room:
                out.append((d, int(a)))
        return out

    def door_approach(self, door: int, room: int) -> FloatArray:
        """(2,) the point `drive_margin_m` inside `room` on the door's normal."""
        centre = self.doors[door]
        inward = self.room_centre(room) - centre
        return centre + self.drive_margin_m * inward / np.linalg.norm(inward)


def _segment_distance(p: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """(N,) distance of (N, 2) points to the segment from a (2,) to b (2,)."""
    ab = b - a
    s = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + s[:, None] * ab), axis=1)


def make_world(
    *,
    rooms: tuple[int, int] = (3, 3),
    room_size_m: float = 6.0,
    landmarks: int = 225,
    rng: np.random.Generator,
    door_width_m: float = 1.0,
    drive_margin_m: float = 1.0,
    clearance_m: float = 0.5,
) -> IndoorWorld:
    """Generate a world: rooms in a grid, a door between every two neighbours.

    Landmarks are spread evenly over the rooms (the first rooms get the
    remainder) and lie in a band along the walls, between 0.05 m and
    ``drive_margin_m - clearance_m`` from a wall, outside the door gaps and at
    least `clearance_m` from the robot's door passages, so never within
    `clearance_m` of where the robot drives.
    """
    nx, ny = rooms
    size = room_size_m
    band_hi = drive_margin_m - clearance_m
    if nx < 1 or ny < 1 or nx * ny < 2:
        raise ValueError(f"need at least two rooms, got {rooms}")
    if band_hi <= _WALL_OFFSET_M or 2.0 * drive_margin_m >= size:
        raise ValueError("drive_margin_m must exceed clearance_m + 0.05 and be < room_size_m/2")
    if door_width_m >= size - 2.0 * _WALL_OFFSET_M:
        raise ValueError("door_width_m does not fit the room")

    centres: list[tuple[float, float]] = []
    pairs: list[tuple[int, int]] = []
    for iy in range(ny):
        for ix in range(nx):
            room = iy * nx + ix
            if ix + 1 < nx:
                centres.append(((ix + 1) * size, (iy + 0.5) * size))
                pairs.append((room, room + 1))
            if iy + 1 < ny:
                centres.append(((ix + 0.5) * size, (iy + 1) * size))
                pairs.append((room, room + nx))
    world = IndoorWorld(
        rooms=(nx, ny),
        room_size_m=size,
        door_width_m=door_width_m,
        drive_margin_m=drive_margin_m,
        doors=np.array(centres, dtype=np.float64),
        door_rooms=np.array(pairs, dtype=np.int64),
        landmarks=np.empty((0, 2)),
        landmark_ids=np.empty(0, dtype=np.int64),
        landmark_rooms=np.empty(0, dtype=np.int64),
    )

    n_rooms = nx * ny
    counts = np.full(n_rooms, landmarks // n_rooms)
    counts[: landmarks % n_rooms] += 1
    keep_out = max(clearance_m, 0.5 * door_width_m)
    points: list[FloatArray] = []
    for room in range(n_rooms):
        passages = [
            (world.doors[d], world.door_approach(d, room)) for d, _ in world.neighbours(room)
        ]
        found = np.empty((0, 2))
        while len(found) < counts[room]:
            n = 4 * int(counts[room]) + 8
            along = rng.uniform(_WALL_OFFSET_M, size - _WALL_OFFSET_M, n)
            depth = rng.uniform(_WALL_OFFSET_M, band_hi, n)
            wall = rng.integers(0, 4, n)  # bottom, right, top, left
            local = np.select(
                [wall[:, None] == 0, wall[:, None] == 1, wall[:, None] == 2],
                [
                    np.column_stack([along, depth]),
                    np.column_stack([size - depth, along]),
                    np.column_stack([along, size - depth]),
                ],
                np.column_stack([depth, along]),
            )
            cand = world.room_origin(room) + local
            ok = np.ones(n, dtype=bool)
            for door_centre, approach in passages:
                ok &= _segment_distance(cand, door_centre, approach) >= keep_out
            found = np.vstack([found, cand[ok]])
        points.append(found[: counts[room]])

    return IndoorWorld(
        rooms=world.rooms,
        room_size_m=size,
        door_width_m=door_width_m,
        drive_margin_m=drive_margin_m,
        doors=world.doors,
        door_rooms=world.door_rooms,
        landmarks=np.vstack(points),
        landmark_ids=np.arange(landmarks, dtype=np.int64),
        landmark_rooms=np.repeat(np.arange(n_rooms, dtype=np.int64), counts),
    )


def bearings_from_pose(pose_xytheta: ArrayLike, points_xy: ArrayLike) -> FloatArray:
    """(K,) bearings (rad, CCW from forward, wrapped) of (K, 2) points from a (3,) pose."""
    x, y, theta = np.asarray(pose_xytheta, dtype=np.float64)
    p = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    return wrap_angles(np.arctan2(p[:, 1] - y, p[:, 0] - x) - theta)


def noisy_observations(
    rel_xy: FloatArray,
    theta: float,
    labels: list[str],
    bearing_sigma_rad: float,
    rng: np.random.Generator,
) -> tuple[BearingObservation, ...]:
    """Observations of (K,) points at (K, 2) offsets `rel_xy` (metres, map axes) from a
    robot heading `theta` (rad): bearing = truth + N(0, bearing_sigma_rad), wrapped;
    ``sigma`` = bearing_sigma_rad (None if 0); the given labels."""
    true = np.arctan2(rel_xy[:, 1], rel_xy[:, 0]) - theta
    bearing = wrap_angles(true + rng.normal(0.0, bearing_sigma_rad, len(rel_xy)))
    sigma = bearing_sigma_rad if bearing_sigma_rad > 0 else None
    return tuple(
        BearingObservation(bearing_rad=b, label=label, sigma_rad=sigma)
        for b, label in zip(bearing.tolist(), labels, strict=True)
    )


@dataclass(frozen=True)
class SimRun:
    """A simulated run: the frames a robot would send and what really happened.

    Attributes:
        frames: one robot's frames, seq 0, 1, ...; the first has `initial_pose`.
        ground_truth: the true pose at each frame's stamp.
        landmarks: (M, 2) true landmark positions, metres.
        landmark_ids: (M,) their ids (observation labels are ``str(id)``).
        world: the world the run took place in (this module's, or the outdoor one of
            service.offline.datasets.outdoor_sim).
    """

    frames: list[FrameInput]
    ground_truth: Trajectory
    landmarks: FloatArray
    landmark_ids: IntArray
    world: IndoorWorld | OutdoorWorld


def simulate(
    world: IndoorWorld,
    *,
    frames: int,
    rng: np.random.Generator,
    step_m: float = 0.1,
    turn_step_rad: float = 0.3,
    odometry_noise: tuple[float, float, float] = (0.02, 0.02, 0.01),
    bearing_sigma_rad: float = float(np.deg2rad(1.0)),
    max_range_m: float = 5.0,
    max_observations: int = 10,
    door_probability: float = 0.4,
    frame_period_s: float = 0.1,
    robot: str = "r1",
) -> SimRun:
    """Drive a robot through the world and record its frames.

    Motion: the robot starts at a random point of room 0 with a random heading
    and follows waypoints (random points of the drive area of its room; with
    probability `door_probability` instead the passage through a random door,
    straight along the door's normal, and a random point of the next room). Each
    frame it either turns in place by `turn_step_rad` towards the next waypoint
    or, once facing it within `turn_step_rad`, turns onto it and drives up to
    `step_m` (stopping at the waypoint).

    Odometry (frames 1, 2, ...): the true motion (dx, dy, dtheta) in the
    previous robot frame plus independent Gaussian noise with sigmas
    ``(kx d, ky d, kt (d + |dtheta|))`` for ``odometry_noise = (kx, ky, kt)``, d
    the distance travelled in metres (kx, ky in m/m; kt in rad/m and rad/rad).
    The sigmas are not put in the frames (the map's own model applies).

    Observations: the landmarks of the robot's room within `max_range_m`,
    nearest first, at most `max_observations`; bearing = truth + N(0,
    bearing_sigma_rad), wrapped; ``sigma`` = bearing_sigma_rad (None if 0);
    label = str(landmark id).

    Stamps are ``seq * frame_period_s`` seconds.
    """
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    kx, ky, kt = odometry_noise
    size, margin = world.room_size_m, world.drive_margin_m
    per_room = [np.flatnonzero(world.landmark_rooms == r) for r in range(world.n_rooms)]

    def random_point(room: int) -> FloatArray:
        return world.room_origin(room) + margin + rng.random(2) * (size - 2.0 * margin)

    labels = [str(i) for i in world.landmark_ids.tolist()]
    nx, ny = world.rooms

    def observe(pos: FloatArray, theta: float) -> tuple[BearingObservation, ...]:
        ix, iy = math.floor(pos[0] / size), math.floor(pos[1] / size)  # as IndoorWorld.room_of
        if not (0 <= ix < nx and 0 <= iy < ny):
            return ()
        idx = per_room[iy * nx + ix]
        rel = world.landmarks[idx] - pos
        dist = np.hypot(rel[:, 0], rel[:, 1])
        near = np.flatnonzero(dist <= max_range_m)
        near = near[np.argsort(dist[near], kind="stable")][:max_observations]
        return noisy_observations(
            rel[near], theta, [labels[i] for i in idx[near].tolist()], bearing_sigma_rad, rng
        )

    pos = random_point(0)
    theta = float(rng.uniform(-math.pi, math.pi))
    plan_room = 0
    path: deque[FloatArray] = deque()
    truth = np.empty((frames, 3))
    truth[0] = (pos[0], pos[1], theta)
    out = [
        FrameInput(
            robot=robot,
            seq=0,
            stamp=0.0,
            initial_pose=Pose2D(float(pos[0]), float(pos[1]), theta),
            observations=observe(pos, theta),
        )
    ]
    for seq in range(1, frames):
        while True:
            if not path:
                if rng.random() < door_probability:
                    options = world.neighbours(plan_room)
                    door, nxt = options[int(rng.integers(len(options)))]
                    path.extend(
                        [
                            world.door_approach(door, plan_room),
                            world.doors[door],
                            world.door_approach(door, nxt),
                            random_point(nxt),
                        ]
                    )
                    plan_room = nxt
                else:
                    path.append(random_point(plan_room))
            target = path[0]
            vec = target - pos
            dist = float(np.hypot(vec[0], vec[1]))
            if dist > 1e-9:
                break
            path.popleft()
        error = wrap_angle(math.atan2(vec[1], vec[0]) - theta)
        if abs(error) > turn_step_rad:  # turn in place towards the waypoint
            turn, travel = math.copysign(turn_step_rad, error), 0.0
            theta = wrap_angle(theta + turn)
        elif dist <= step_m:  # face the waypoint and reach it
            turn, travel = error, dist
            theta = wrap_angle(theta + turn)
            pos = target.copy()
            path.popleft()
        else:  # face the waypoint and drive towards it
            turn, travel = error, step_m
            theta = wrap_angle(theta + turn)
            pos = pos + travel * np.array([math.cos(theta), math.sin(theta)])
        truth[seq] = (pos[0], pos[1], theta)
        noise = rng.normal(0.0, 1.0, 3) * (kx * travel, ky * travel, kt * (travel + abs(turn)))
        odo = Odometry(
            dx=travel * math.cos(turn) + float(noise[0]),
            dy=travel * math.sin(turn) + float(noise[1]),
            dtheta=wrap_angle(turn + float(noise[2])),
        )
        out.append(
            FrameInput(
                robot=robot,
                seq=seq,
                stamp=seq * frame_period_s,
                odometry=odo,
                observations=observe(pos, theta),
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


def write_run(
    run: SimRun, frames_path: str | os.PathLike[str], gt_path: str | os.PathLike[str]
) -> None:
    """Write the frames as JSON lines and the ground truth as TUM."""
    write_frames(frames_path, run.frames)
    write_tum(gt_path, run.ground_truth)
