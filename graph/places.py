"""Learnt places and yaw-invariant place recognition (Thompson & Zelinsky, DESIGN.md).

A place is a reference pose in the map frame and a few landmarks seen from it,
chosen for static uniqueness (they do not look like the rest of the view) and
dynamic reliability (they were matched in most recent frames), spread over all
directions. Each keeps its bearing from the reference pose (robot frame), its
depth and depth variance (from the graph's landmark estimate and covariance) and
an appearance signature: the label for labelled observations; the descriptor /
patch bytes when the frontend provides one.

Recognition (labelled observations): for place p, every observed landmark that
p also holds gives a residual ``r = wrap(z - beta)``; rotating the robot by
``delta`` shifts every bearing by ``-delta``, so the place's yaw offset is the
weighted circular mean of its residuals -- the score does not depend on the
robot's heading (a panorama column shift is a rotation). The score is the share
of the current observations that p explains within ``match_sigma_rad`` after the
yaw offset, times ``1 - 0.5^m`` for m agreeing landmarks (two agreeing landmarks
say more than one), times the paper's decay with the distance from the current
best place. One query is a handful of numpy operations over all places' landmarks
(linear in their number; no loop over places).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from graph.angles import wrap_angle, wrap_angles
from graph.types import Pose2D

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class PlaceConfig:
    """Parameters of place learning and recognition (SI units, radians)."""

    max_landmarks: int = 12
    """Most landmarks a place keeps."""
    min_landmarks: int = 2
    """Fewest landmarks a place needs to be learnt."""
    sectors: int = 8
    """Directions (equal sectors of the full circle) the selection spreads over."""
    max_depth_m: float = 8.0
    """Landmarks farther than this from the reference pose are not taken."""
    learn_distance_m: float = 1.5
    """A robot farther than this from every place learns a new one."""
    weak_score: float = 0.3
    """Below this best score, recognition is weak: learn a place if at least half of
    learn_distance_m from every place."""
    match_sigma_rad: float = math.radians(12.0)
    """Tolerance of a bearing's agreement after the place's yaw offset (it absorbs the
    parallax of a robot standing away from the reference pose)."""
    decay_m: float = 3.0
    """Recognition decays as exp(-d / decay_m) with d the distance to the current place."""
    decay_floor: float = 0.2
    """Decay never goes below this factor (a far place can still win)."""


@dataclass(frozen=True, slots=True)
class PlaceLandmark:
    """One landmark of a place, as seen from the place's reference pose."""

    label: str
    landmark_id: int
    bearing_rad: float
    """Robot-frame bearing from the reference pose, CCW from +x, wrapped."""
    depth_m: float
    depth_var_m2: float
    """Variance of the depth along the ray, from the landmark's marginal covariance."""
    uniqueness: float
    """Static uniqueness in [0, 1] (1 for a labelled landmark: its label is unique)."""
    reliability: float
    """Dynamic reliability in [0, 1]: share of recent frames in which it was matched."""
    signature: bytes | None = None
    """Descriptor / patch bytes for image observations; None for labelled ones."""

    @property
    def weight(self) -> float:
        return self.uniqueness * self.reliability


@dataclass(frozen=True, slots=True)
class Place:
    id: int
    pose: Pose2D
    landmarks: tuple[PlaceLandmark, ...]
    robot: str
    frame: int
    stamp: float


@dataclass(slots=True)
class Transition:
    """Consecutive visits from one place to another: the topological map's edge."""

    source: int
    target: int
    heading_rad: float
    """Direction of the target's reference position seen from the source's, map frame."""
    distance_m: float
    count: int = 1


@dataclass(frozen=True, slots=True)
class LandmarkCandidate:
    """A live landmark offered for a new place (map position and its covariance)."""

    label: str
    landmark_id: int
    position_xy: tuple[float, float]
    covariance: FloatArray
    """(2, 2) marginal covariance, m^2."""
    reliability: float
    uniqueness: float = 1.0
    signature: bytes | None = None


@dataclass(frozen=True, slots=True)
class Recognition:
    """Scores of every place for one frame, best first."""

    place_ids: NDArray[np.int64]
    scores: FloatArray
    yaw_offsets_rad: FloatArray
    """delta per place: the robot's heading is about place.theta - delta."""

    @property
    def best(self) -> int | None:
        return int(self.place_ids[0]) if len(self.place_ids) and self.scores[0] > 0 else None

    @property
    def best_score(self) -> float:
        return float(self.scores[0]) if len(self.scores) else 0.0


def select_landmarks(
    pose: Pose2D, candidates: Sequence[LandmarkCandidate], config: PlaceConfig
) -> tuple[PlaceLandmark, ...]:
    """The landmarks of a place at `pose`: the best (uniqueness x reliability, less depth
    uncertainty) of each direction sector first, then the next best, up to the cap."""
    rows: list[tuple[float, int, PlaceLandmark]] = []
    for c in candidates:
        dx, dy = c.position_xy[0] - pose.x, c.position_xy[1] - pose.y
        depth = math.hypot(dx, dy)
        if depth <= 1e-6 or depth > config.max_depth_m or c.reliability <= 0:
            continue
        u = np.array([dx, dy]) / depth
        var = float(u @ np.asarray(c.covariance) @ u)
        bearing = wrap_angle(math.atan2(dy, dx) - pose.theta)
        lm = PlaceLandmark(
            c.label, c.landmark_id, bearing, depth, var, c.uniqueness, c.reliability, c.signature
        )
        score = lm.weight / (1.0 + var)
        sector = int((bearing + math.pi) / (2 * math.pi) * config.sectors) % config.sectors
        rows.append((score, sector, lm))
    rows.sort(key=lambda r: -r[0])
    first: list[PlaceLandmark] = []
    rest: list[PlaceLandmark] = []
    used: set[int] = set()
    for _, sector, lm in rows:
        (rest if sector in used else first).append(lm)
        used.add(sector)
    return tuple((first + rest)[: config.max_landmarks])


@dataclass
class PlaceMap:
    """Places, their transitions, and the flat arrays recognition runs on."""

    config: PlaceConfig = field(default_factory=PlaceConfig)
    places: list[Place] = field(default_factory=list)
    transitions: dict[tuple[int, int], Transition] = field(default_factory=dict)
    last_visited: dict[str, int] = field(default_factory=dict)
    _vocab: dict[str, int] = field(default_factory=dict)
    _owner: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    _code: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    _bearing: FloatArray = field(default_factory=lambda: np.zeros(0))
    _weight: FloatArray = field(default_factory=lambda: np.zeros(0))
    _xy: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))

    def __len__(self) -> int:
        return len(self.places)

    # ------------------------------------------------------------ learning
    def learn(
        self,
        pose: Pose2D,
        candidates: Sequence[LandmarkCandidate],
        *,
        robot: str,
        frame: int,
        stamp: float,
    ) -> Place | None:
        """Add a place at `pose` from the candidates; None if too few qualify."""
        chosen = select_landmarks(pose, candidates, self.config)
        if len(chosen) < self.config.min_landmarks:
            return None
        place = Place(len(self.places), pose, chosen, robot, frame, stamp)
        self.places.append(place)
        codes = [self._vocab.setdefault(lm.label, len(self._vocab)) for lm in chosen]
        self._owner = np.concatenate([self._owner, np.full(len(chosen), place.id)])
        self._code = np.concatenate([self._code, np.asarray(codes, dtype=np.int64)])
        self._bearing = np.concatenate([self._bearing, [lm.bearing_rad for lm in chosen]])
        self._weight = np.concatenate([self._weight, [lm.weight for lm in chosen]])
        self._xy = np.vstack([self._xy, [[pose.x, pose.y]]])
        return place

    def nearest(self, xy: Sequence[float] | FloatArray) -> tuple[int | None, float]:
        """(id, distance m) of the place whose reference position is nearest `xy`."""
        if not self.places:
            return None, math.inf
        d = np.hypot(self._xy[:, 0] - xy[0], self._xy[:, 1] - xy[1])
        i = int(np.argmin(d))
        return i, float(d[i])

    def should_learn(self, xy: Sequence[float] | FloatArray, best_score: float) -> bool:
        """Far from every place, or recognition weak and not close to any place."""
        _, d = self.nearest(xy)
        far = d > self.config.learn_distance_m
        weak = best_score < self.config.weak_score and d > 0.5 * self.config.learn_distance_m
        return far or weak

    def visit(self, robot: str, place_id: int) -> Transition | None:
        """Record that `robot` is at `place_id`; a change of place adds a transition."""
        previous = self.last_visited.get(robot)
        self.last_visited[robot] = place_id
        if previous is None or previous == place_id:
            return None
        key = (previous, place_id)
        if key in self.transitions:
            self.transitions[key].count += 1
            return self.transitions[key]
        a, b = self._xy[previous], self._xy[place_id]
        t = Transition(
            previous,
            place_id,
            math.atan2(b[1] - a[1], b[0] - a[0]),
            float(np.hypot(*(b - a))),
        )
        self.transitions[key] = t
        return t

    # ------------------------------------------------------------ recognition
    def recognise(
        self,
        labels: Sequence[str],
        bearings_rad: Sequence[float],
        quality: Sequence[float] | None = None,
        *,
        current: int | None = None,
    ) -> Recognition:
        """Score every place against one frame's labelled observations (yaw-invariant)."""
        n_places = len(self.places)
        empty = Recognition(np.zeros(0, np.int64), np.zeros(0), np.zeros(0))
        if n_places == 0:
            return empty
        z_by_code = np.full(len(self._vocab) + 1, np.nan)
        q_by_code = np.zeros(len(self._vocab) + 1)
        known = 0.0
        for i, (label, bearing) in enumerate(zip(labels, bearings_rad, strict=True)):
            code = self._vocab.get(label)
            if code is None:
                continue
            z_by_code[code] = bearing
            q_by_code[code] = 1.0 if quality is None else float(quality[i])
            known += q_by_code[code]
        z = z_by_code[self._code]
        hit = ~np.isnan(z)
        owner = self._owner[hit]
        w = self._weight[hit] * q_by_code[self._code[hit]]
        r = wrap_angles(z[hit] - self._bearing[hit])
        s = np.bincount(owner, w * np.sin(r), minlength=n_places)
        c = np.bincount(owner, w * np.cos(r), minlength=n_places)
        delta = np.arctan2(s, c)
        e = wrap_angles(r - delta[owner])
        agree = np.exp(-0.5 * (e / self.config.match_sigma_rad) ** 2)
        explained = np.bincount(owner, w * agree, minlength=n_places) / max(known, 1e-9)
        m = np.bincount(owner, agree, minlength=n_places)
        scores = np.minimum(explained, 1.0) * (1.0 - 0.5**m)
        if current is not None and 0 <= current < n_places:
            d = np.hypot(*(self._xy - self._xy[current]).T)
            floor = self.config.decay_floor
            scores = scores * (floor + (1.0 - floor) * np.exp(-d / self.config.decay_m))
        order = np.lexsort((np.arange(n_places), -scores))
        return Recognition(order.astype(np.int64), scores[order], delta[order])
