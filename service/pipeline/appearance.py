"""Places of a camera map recognised by appearance (frontend.appearance).

A camera map's panoramas say where the robot is: the map keeps an appearance place --
the panorama's signature at the robot's graph pose -- whenever the robot is
`learn_distance_m` from every such place, and every image frame is matched against all
of them (yaw-invariant: a rotation is a column shift). The frame result reports the best
place whose score reaches `min_score`, and the score as its confidence; the best places
(`hints`) are where a camera robot's particle filter injects its proposals
(service.pipeline.map_pipeline).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from frontend.appearance import AppearanceIndex, AppearanceMatch
from graph.angles import wrap_angle

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class AppearancePlace:
    id: int
    pose: tuple[float, float, float]
    """Graph pose (x m, y m, theta rad) where the signature was taken."""
    robot: str
    frame: int
    stamp: float


@dataclass
class AppearancePlaces:
    learn_distance_m: float = 1.5
    min_score: float = 0.5
    """Normalised cross-correlation a place needs to be reported as recognised."""
    index: AppearanceIndex = field(default_factory=AppearanceIndex)
    places: list[AppearancePlace] = field(default_factory=list)

    def match(self, signature: NDArray[np.float32]) -> AppearanceMatch | None:
        """Every place's score and yaw offset for this signature (None: no place yet)."""
        return self.index.match(signature) if self.places else None

    def best(self, found: AppearanceMatch | None) -> tuple[int | None, float | None]:
        """(best place if it scores at least min_score, else None; its score or None)."""
        if found is None or len(found.scores) == 0:
            return None, None
        top = int(found.order[0])
        score = float(found.scores[top])
        return (top if score >= self.min_score else None), score

    def hints(
        self, found: AppearanceMatch | None, *, top: int = 3
    ) -> list[tuple[FloatArray, float]]:
        """(pose (3,), weight) of the `top` best places scoring at least min_score: the
        place's position and its heading turned by the recognised yaw offset (query yaw
        - place yaw), i.e. where the robot would be standing on the place; weight = the
        score's excess over the median place's (a view every place explains alike
        proposes nothing)."""
        if found is None or len(found.scores) == 0:
            return []
        baseline = float(np.median(found.scores)) if len(found.scores) > 2 else 0.0
        out: list[tuple[FloatArray, float]] = []
        for i in found.order[:top].tolist():
            score = float(found.scores[i])
            if score < self.min_score or score <= baseline:
                continue
            x, y, theta = self.places[i].pose
            yaw = wrap_angle(theta + float(found.yaw_offsets_rad[i]))
            out.append((np.array([x, y, yaw]), score - baseline))
        return out

    def observe(
        self,
        signature: NDArray[np.float32],
        *,
        robot: str,
        pose: tuple[float, float, float],
        frame: int,
        stamp: float,
        found: AppearanceMatch | None = None,
    ) -> tuple[int | None, float | None, AppearancePlace | None]:
        """Recognise (best place or None, its score or None), then learn a place here if
        the robot is far from every place: (place, confidence, learnt). `found`: this
        signature's `match`, if already computed."""
        best, score = self.best(found if found is not None else self.match(signature))
        near = min(
            (math.hypot(p.pose[0] - pose[0], p.pose[1] - pose[1]) for p in self.places),
            default=math.inf,
        )
        learnt = None
        if near > self.learn_distance_m:
            learnt = AppearancePlace(self.index.add(signature), pose, robot, frame, stamp)
            self.places.append(learnt)
            best, score = learnt.id, 1.0
        return best, score, learnt

    def doc(self) -> list[dict[str, Any]]:
        return [
            {
                "id": p.id,
                "pose": {"x": p.pose[0], "y": p.pose[1], "theta": p.pose[2]},
                "robot": p.robot,
                "frame": p.frame,
                "stamp": p.stamp,
            }
            for p in self.places
        ]
