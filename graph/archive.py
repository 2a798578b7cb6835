"""Long-term memory of landmarks: the landmarks the budget removed from the graph.

RTAB-Map's working / long-term memory, for landmarks. The live landmarks (the
graph's, bounded by the cap) are the working memory; a landmark the policy removes
is marginalised (its information stays in the graph, as a marginal on the poses that
saw it) and its last state is archived here: label, last estimate and (2, 2)
marginal covariance, E(X) and count, when and why it left. Seen again (by label), it
comes back under its own id, initialised from the archive at once (see
BearingSlam._restore for what goes into the graph and why). The archive
holds one entry per distinct landmark that is not live (and keeps the entries of
those live again, for their next removal): it grows with distinct landmarks, never
with time.

A restored landmark is a new variable that only its new bearings and a weak prior
at the archived estimate hold (its earlier observations are in the marginal on the
poses, not on it). Removed again after a few bearings, its estimate is worse
determined than the archived one it started from; archiving that would let a
landmark that churns walk along its rays, a few bearings at a time. So an entry
keeps the estimate (position and covariance) whose worst direction is better known:
the new one if its covariance's largest eigenvalue is smaller, else the archived one.

Hysteresis (`admits`, SlamConfig.restore_after_frames and restore_min_rays): a landmark
removed fewer than N frames ago comes back only once it was observed k times since, so that a
landmark the policy has just judged least useful does not churn in and out of the
graph frame after frame.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from graph.landmarks import LandmarkRecord


@dataclass(slots=True)
class ArchivedLandmark:
    """A removed landmark's last state. Units: metres, m^2, seconds; frames are the
    estimator's frame indices."""

    id: int
    label: str
    position: tuple[float, float]
    """Last estimate before its removal, map frame."""
    covariance: tuple[float, float, float, float]
    """(2, 2) marginal covariance then, row-major."""
    observed_from: tuple[float, float]
    """E(X): mean robot position it was observed from."""
    count: int
    """Observations E(X) is the mean of."""
    first_stamp: float
    last_stamp: float
    removed_frame: int
    removed_stamp: float
    policy: str
    reason: str
    removals: int = 1
    """Times it was removed (a restored landmark may be removed again)."""
    restorations: int = 0
    """Times it came back from the archive."""

    @property
    def covariance_matrix(self) -> NDArray[np.float64]:
        return np.asarray(self.covariance, dtype=np.float64).reshape(2, 2)

    def information(self) -> float:
        """I = 1/sigma_xx^2 + 1/sigma_yy^2 of the archived covariance (policies' eq. 3-4)."""
        cov = self.covariance_matrix
        return float(1.0 / cov[0, 0] + 1.0 / cov[1, 1])

    def as_dict(self) -> dict[str, Any]:
        """The REST document of an archived landmark."""
        return {
            "id": self.id,
            "label": self.label,
            "x": self.position[0],
            "y": self.position[1],
            "covariance": self.covariance_matrix.tolist(),
            "information": self.information(),
            "observed_from": {
                "x": self.observed_from[0],
                "y": self.observed_from[1],
                "n": self.count,
            },
            "first_stamp": self.first_stamp,
            "last_stamp": self.last_stamp,
            "removed_frame": self.removed_frame,
            "removed_stamp": self.removed_stamp,
            "policy": self.policy,
            "reason": self.reason,
            "removals": self.removals,
            "restorations": self.restorations,
        }


class LandmarkArchive:
    """Archived landmarks by id, with an index from label to the newest id."""

    def __init__(self) -> None:
        self._entries: dict[int, ArchivedLandmark] = {}
        self._by_label: dict[str, int] = {}
        self._live: dict[int, ArchivedLandmark] = {}
        """The entries of landmarks restored to the graph (see `put`)."""

    def __repr__(self) -> str:
        return f"LandmarkArchive({list(self._entries.values())!r})"

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, LandmarkArchive):
            return NotImplemented
        return (self._entries, self._by_label, self._live) == (
            other._entries,
            other._by_label,
            other._live,
        )

    __hash__ = None  # type: ignore[assignment]

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, landmark_id: object) -> bool:
        return landmark_id in self._entries

    def __iter__(self) -> Iterator[ArchivedLandmark]:
        return iter(self._entries.values())

    def get(self, landmark_id: int) -> ArchivedLandmark | None:
        return self._entries.get(landmark_id)

    def by_label(self, label: str) -> ArchivedLandmark | None:
        """The archived landmark a label names (None: the label is not archived)."""
        lid = self._by_label.get(label)
        return None if lid is None else self._entries[lid]

    def put(
        self,
        record: LandmarkRecord,
        *,
        position: NDArray[np.float64],
        covariance: NDArray[np.float64],
        frame: int,
        stamp: float,
        policy: str,
        reason: str,
    ) -> ArchivedLandmark:
        """Archive a landmark the budget just removed (`record` is its live record); of
        its estimate and the one archived before it was restored, the better determined
        (see the module docstring)."""
        cov = np.asarray(covariance, dtype=np.float64).reshape(2, 2)
        position = np.asarray(position, dtype=np.float64)
        before = self._live.pop(record.id, None)
        if before is not None and _worst_variance(before.covariance_matrix) < _worst_variance(cov):
            position, cov = np.array(before.position), before.covariance_matrix
        entry = ArchivedLandmark(
            id=record.id,
            label=record.label,
            position=(float(position[0]), float(position[1])),
            covariance=(float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 0]), float(cov[1, 1])),
            observed_from=(float(record.observed_from[0]), float(record.observed_from[1])),
            count=record.count,
            first_stamp=record.first_stamp,
            last_stamp=record.last_stamp,
            removed_frame=frame,
            removed_stamp=stamp,
            policy=policy,
            reason=reason,
            removals=record.removals + 1,
            restorations=record.restorations,
        )
        self._entries[record.id] = entry
        self._by_label[record.label] = record.id
        return entry

    @staticmethod
    def admits(
        entry: ArchivedLandmark,
        frame: int,
        rays: int,
        *,
        after_frames: int,
        min_rays: int,
        backoff: bool = False,
    ) -> bool:
        """May `entry` come back at `frame`, observed `rays` times since its removal?
        Yes once `after_frames` frames went by since, or with `min_rays` observations;
        with `backoff`, both doubled for each removal of it after the first."""
        scale = 2 ** min(entry.removals - 1, 20) if backoff else 1
        return frame - entry.removed_frame >= after_frames * scale or rays >= min_rays * scale

    def take(self, landmark_id: int, frame: int) -> LandmarkRecord:
        """Remove an entry from the archive: the live record it comes back as (same id,
        label, E(X), count; `added_frame` is the frame it re-entered the graph)."""
        entry = self._entries.pop(landmark_id)
        if self._by_label.get(entry.label) == landmark_id:
            del self._by_label[entry.label]
        self._live[landmark_id] = entry
        return LandmarkRecord(
            entry.id,
            entry.label,
            frame,
            entry.first_stamp,
            entry.last_stamp,
            observed_from=np.array(entry.observed_from, dtype=np.float64),
            count=entry.count,
            removals=entry.removals,
            restorations=entry.restorations + 1,
        )


def _worst_variance(covariance: NDArray[np.float64]) -> float:
    """The largest eigenvalue of a (2, 2) covariance, m^2."""
    return float(np.linalg.eigvalsh(covariance)[-1])
