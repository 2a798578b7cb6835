"""Bookkeeping of live landmarks and of candidate tracks awaiting initialisation."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(slots=True)
class LandmarkRecord:
    """A live landmark. `observed_from` is the running mean E(X) of the robot
    positions (map frame, metres) it was observed from, over `count` observations
    (Hochdorfer & Schlegel eq. 1-2)."""

    id: int
    label: str
    added_frame: int
    first_stamp: float
    last_stamp: float
    observed_from: np.ndarray = field(default_factory=lambda: np.zeros(2))
    count: int = 0
    removals: int = 0
    """Times the budget removed it before (it came back from the archive, graph.archive)."""
    restorations: int = 0
    """Times it came back from the archive."""

    def observe(self, position_xy: np.ndarray, stamp: float) -> None:
        """E_n(X) = E_{n-1}(X) + (X_n - E_{n-1}(X)) / n."""
        self.count += 1
        self.observed_from = self.observed_from + (position_xy - self.observed_from) / self.count
        self.last_stamp = max(self.last_stamp, stamp)


@dataclass(frozen=True, slots=True)
class Ray:
    """One observation of a candidate: the pose key it was taken from and its bearing."""

    pose_key: int
    frame: int
    stamp: float
    bearing_rad: float
    sigma_rad: float


@dataclass(slots=True)
class CandidateTrack:
    """An observed landmark not yet in the graph (too little parallax so far)."""

    label: str
    rays: tuple[Ray, ...] = ()
    last_frame: int = 0

    def with_ray(self, ray: Ray, max_rays: int, first: int = 0) -> CandidateTrack:
        """The track with `ray` added: at most `max_rays` rays, the `first` oldest ones
        and the newest others (the oldest rays are the widest baseline, and they tie the
        landmark to where its robot came from, e.g. the pose its initial pose anchors)."""
        rays = (*self.rays, ray)
        if len(rays) > max_rays:
            keep = min(first, max_rays - 1)
            rays = rays[:keep] + rays[len(rays) - (max_rays - keep) :]
        return CandidateTrack(self.label, rays, ray.frame)
