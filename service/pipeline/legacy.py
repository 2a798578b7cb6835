"""The pickled classes of snapshots taken before the map pipeline had its own package,
under the names those snapshots give them (see `older_names`), and their conversion.

Such a snapshot's extra state is a ``MapLocalisation`` (the place localiser, its rng,
each robot's last frame, reported place and landmark-match average, an ``OffGraphLog``
of every robot's off-graph frames, the appearance places); its front-end state is a
dict of the associator and each robot's last pose and panorama signature.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from service.pipeline import appearance
from service.pipeline.offgraph import AnchoredRun, OffGraphFrame, OffGraphTrack
from service.pipeline.robots import RobotState

__all__ = ["AnchoredRun", "MapLocalisation", "OffGraphFrame", "OffGraphLog", "older_names"]


class MapLocalisation:
    """An older snapshot's place localiser state (its attributes as pickled)."""

    localiser: Any
    rng: Any


class OffGraphLog:
    """An older snapshot's off-graph frames: dicts robot -> list / pose."""

    pending: dict[str, list[OffGraphFrame]]
    anchored: dict[str, list[AnchoredRun]]
    reckoned: dict[str, tuple[float, float, float]]
    settled: dict[str, list[OffGraphFrame]]


_NAMES = {
    "service.localisation": sys.modules[__name__],
    "service.offgraph": sys.modules[__name__],
    "service.appearance_places": appearance,
}
"""Module names older snapshots pickled their classes under -> where they are now."""


@contextmanager
def older_names() -> Iterator[None]:
    """While unpickling a snapshot: the module names older snapshots refer to resolve
    to this module (and service.pipeline.appearance); put back afterwards."""
    saved = {name: sys.modules.get(name) for name in _NAMES}
    sys.modules.update(_NAMES)
    try:
        yield
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module


def robots_of(loc: MapLocalisation, frontend: dict[str, Any] | None) -> dict[str, RobotState]:
    """Each robot's state from an older snapshot's localiser and front-end state."""
    state = vars(loc)
    last: dict[str, tuple[int, float]] = state.get("last", {})
    reported: dict[str, tuple[int | None, float | None]] = state.get("reported", {})
    matches: dict[str, float] = state.get("landmark_matches", {})
    log = state.get("off_graph")
    og: dict[str, Any] = {} if log is None else vars(log)
    poses = {} if frontend is None else dict(frontend.get("last", {}))
    signatures = {} if frontend is None else dict(frontend.get("signature", {}))
    names = set(last) | set(reported) | set(matches) | set(poses) | set(signatures)
    for key in ("pending", "anchored", "reckoned", "settled"):
        names |= set(og.get(key, {}))
    robots: dict[str, RobotState] = {}
    for name in sorted(names):
        track = OffGraphTrack(
            pending=list(og.get("pending", {}).get(name, [])),
            anchored=list(og.get("anchored", {}).get(name, [])),
            reckoned=og.get("reckoned", {}).get(name),
            settled=list(og.get("settled", {}).get(name, [])),
        )
        robots[name] = RobotState(
            last=last.get(name),
            reported=reported.get(name, (None, None)),
            pose=poses.get(name),
            signature=signatures.get(name),
            landmark_matches=matches.get(name),
            off_graph=track,
        )
    return robots
