"""The published view of a map: what its reads are answered from, without its worker.

After every change of a map (a frame, a mode switch, a learnt place, an open) the
worker that owns it builds a `MapView` — plain, immutable documents of the map's state
right after that change — and sends it to the API process with its answer. The API
process answers GET summary, pose, live landmarks, places and trajectory from the
latest view it holds, so a read never waits behind the frames the worker is busy with
(its own map's or other maps'). What a view cannot answer (coverage, archived
landmarks, per-frame statistics, a robot known only to the place localiser) still goes
to the worker.

After a frame, a view renews what is cheap: the summary, the places (if a place or a
transition changed) and the pose of the robot that sent it. Three parts may lag behind
the map: the other robots' poses (each covariance costs a marginal of the graph), the
trajectory rows the estimator holds (renewed every HELD_EVERY frames), and the live
landmarks (a joint marginal of all of them). A read of a
lagging part goes to the worker when it has nothing else to do (so a client reads its
own writes) and is answered from the view while the worker is busy; a lagging trajectory
or landmark read then asks for them anew (`RefreshView`, one at a time per map), and a
worker that has been idle for a moment renews everything.

A view crosses the pipe as a `ViewDelta`: only the parts that are not the very objects
of the view sent before it (the places document is kept while no place or transition
changed, the held rows for HELD_EVERY frames, the landmarks until they are renewed), so
that a frame's answer does not carry, pickle and unpickle the whole map's places and
trajectory every time. The API process applies a delta only to the view it was made
from (`serial`); any other it drops, and asks the worker for a whole view.
"""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.queries import Landmarks, Places, Summary, pose_answer
from service.session import MapSession

Doc = dict[str, Any]

HELD_EVERY = 10
"""Frames between two renewals of the held trajectory rows after frames."""

_serials = itertools.count(1)


@dataclass(frozen=True)
class MapView:
    """A map's state after the change of log frame `log_id`, as documents."""

    map_id: str
    log_id: int
    summary: Doc
    pose: Doc
    places: Doc | None
    """None: the map has no place localiser."""
    held: dict[str, NDArray[np.float64]] | None
    """Trajectory rows the estimator held per robot after frame `held_log_id` ((N, 5)
    seq, stamp, x, y, theta); the final rows before them are in the store. None: the
    map has off-graph frames, whose rows only the worker can place."""
    landmarks: list[Doc]
    """The live landmarks (GET /landmarks) after frame `landmarks_log_id`."""
    landmarks_log_id: int
    held_log_id: int
    poses_log_id: int
    """The frame after which every robot's pose was computed (each frame after it
    renewed only its own robot's entry)."""
    places_version: tuple[int, ...] | None = None
    """The place localiser's `places_version` that `places` was made at."""
    serial: tuple[int, int] = (0, 0)
    """(process id, number): names this view among all views built (a delta's base)."""


_PARTS = ("summary", "pose", "places", "held", "landmarks")
"""A view's documents: sent again only when they are new objects."""


@dataclass(frozen=True)
class ViewDelta:
    """A view as sent to the API process: its small fields, and those of its documents
    that are not the objects the view `base` (the one sent before it) held; `base` None:
    every part is here."""

    base: tuple[int, int] | None
    fields: dict[str, Any]

    @property
    def map_id(self) -> str:
        return str(self.fields["map_id"])

    @classmethod
    def between(cls, view: MapView, previous: MapView | None) -> ViewDelta:
        """What to send of `view` when `previous` was sent before it (None: all)."""
        parts = {f.name: getattr(view, f.name) for f in fields(view)}
        if previous is None:
            return cls(None, parts)
        for name in _PARTS:
            if parts[name] is getattr(previous, name):
                del parts[name]
        return cls(previous.serial, parts)

    def apply(self, current: MapView | None) -> MapView | None:
        """The view this delta describes, from the API process's `current` view of the
        map; None when `current` is not the view it was made from."""
        if self.base is None:
            return MapView(**self.fields)
        if current is None or current.serial != self.base:
            return None
        # dataclasses.replace(current, **fields), without its per-call introspection (the
        # API process applies a delta with every frame)
        view = object.__new__(MapView)
        view.__dict__.update(current.__dict__)
        view.__dict__.update(self.fields)
        return view


def build_view(
    session: MapSession,
    *,
    previous: MapView | None = None,
    robot: str | None = None,
    refresh: bool = False,
) -> MapView:
    """The view of an open map now, in one of three ways (with the map's `previous`
    view; without one, or with neither `robot` nor `refresh`, everything is new):

    - `robot`: after a frame of that robot: the summary, the places (if they changed)
      and that robot's entry of the poses are new, and every HELD_EVERY frames the held
      rows; the rest is `previous`'s (every other robot's pose moved a little with the
      frame's update, but its covariance would cost a marginal of the graph).
    - `refresh`: the live landmarks and the held rows are new (a read found them
      behind), the poses are `previous`'s.
    """
    pipeline = session.pipeline
    log_id = session.last_log_id
    off_graph = bool(pipeline.off_graph_robots())
    held: dict[str, NDArray[np.float64]] | None
    renew_all = previous is None or (robot is None and not refresh)
    if previous is None or renew_all:
        pose, poses_log_id = pose_answer(session), log_id
        held, held_log_id = None, log_id  # below
        landmarks, landmarks_log_id = Landmarks().answer(session), log_id
    elif robot is not None:
        fresh = pose_answer(session, robot)
        pose = {**fresh, "robots": {**previous.pose["robots"], **fresh["robots"]}}
        alone = set(pose["robots"]) <= {robot}  # no other robot's pose to lag
        poses_log_id = log_id if alone else previous.poses_log_id
        held, held_log_id = previous.held, previous.held_log_id
        if held is None or log_id - held_log_id >= HELD_EVERY:
            held, held_log_id = None, log_id  # all robots' rows: below
        landmarks, landmarks_log_id = previous.landmarks, previous.landmarks_log_id
    else:
        pose, poses_log_id = previous.pose, previous.poses_log_id
        held, held_log_id = None, log_id  # below
        landmarks, landmarks_log_id = Landmarks().answer(session), log_id
    if off_graph:
        held = None
    elif held is None:
        held, held_log_id = session.slam.trajectory(), log_id
    places, places_version = None, None
    if pipeline.localiser is not None:
        places_version = pipeline.localiser.places_version()
        if renew_all or previous is None or previous.places_version != places_version:
            places = Places().answer(session)
        else:
            places = previous.places  # no place or transition changed since
    return MapView(
        map_id=session.record.id,
        log_id=log_id,
        summary=Summary().answer(session),
        pose=pose,
        places=places,
        held=held,
        landmarks=landmarks,
        landmarks_log_id=landmarks_log_id,
        held_log_id=held_log_id,
        poses_log_id=poses_log_id,
        places_version=places_version,
        serial=(os.getpid(), next(_serials)),
    )
