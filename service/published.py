"""The published view of a map: what its reads are answered from, without its worker.

After every change of a map (a frame, a mode switch, a learnt place, an open) the
worker that owns it builds a `MapView` — plain, immutable documents of the map's state
right after that change — and sends it to the API process with its answer. The API
process answers GET summary, pose, live landmarks, places and trajectory from the
latest view it holds, so a read never waits behind the frames the worker is busy with
(its own map's or other maps'). What a view cannot answer (coverage, archived
landmarks, per-frame statistics, a robot known only to the place localiser) still goes
to the worker.

Two parts of a view may lag behind the map: the poses and held trajectory rows of the
robots that did not send the last frame, and the live landmarks. A read of such a part
goes to the worker when it has nothing else to do (so a client reads its own writes),
and is answered from the view while the worker is busy.

The live landmarks' marginal covariances cost a joint marginal of every live landmark
(~5 ms for 50 landmarks, half a frame): the view keeps the last landmark document it
had, and the worker computes a new one only when a read found it behind the map (the
API process then asks for it with `RefreshView`, once at a time) or when it is idle
(`landmarks_log_id` says which frame the document is of).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from service.queries import Landmarks, Places, Summary, pose_answer
from service.session import MapSession

Doc = dict[str, Any]


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
    """Trajectory rows the estimator still holds per robot ((N, 5) seq, stamp, x, y,
    theta); the final rows before them are in the store. None: the map has off-graph
    frames, whose rows only the worker can place."""
    landmarks: list[Doc] | None
    """The live landmarks (GET /landmarks), of frame `landmarks_log_id`; None: not
    refreshed with this view (the previous view's stand)."""
    landmarks_log_id: int = 0
    poses_log_id: int = 0
    """The frame after which every robot's pose and held rows were computed (`pose`
    and `held` renew only the robot of each frame after it)."""

    def updated(self, previous: MapView | None) -> MapView:
        """This view, with `previous`'s landmarks when it carries none."""
        if self.landmarks is not None or previous is None or previous.landmarks is None:
            return self
        return replace(
            self, landmarks=previous.landmarks, landmarks_log_id=previous.landmarks_log_id
        )


def build_view(
    session: MapSession,
    *,
    landmarks: bool,
    robot: str | None = None,
    previous: MapView | None = None,
    poses: bool = True,
) -> MapView:
    """The view of an open map now; `landmarks`: with the live landmarks' document;
    `poses` False (with `previous`): the poses as they were published (nothing moved).

    `robot` (with the map's `previous` view): only that robot sent a frame since, so
    only its entries of the poses and the held trajectory rows are new and the other
    robots keep theirs: as of their own latest frame. (Their poses moved a little with
    this frame's update, but each one's covariance would cost a marginal of the graph,
    ~1.5 ms a robot, half a frame's time for a map of four robots; all robots' rows
    ~0.5 ms.) `poses_log_id` says which frame every robot's entries are of."""
    pipeline = session.pipeline
    held: dict[str, NDArray[np.float64]] | None = None
    if previous is not None and not poses:
        pose, held, poses_log_id = previous.pose, previous.held, previous.poses_log_id
    elif robot is None or previous is None or previous.held is None:
        pose, poses_log_id = pose_answer(session), session.last_log_id
    else:
        fresh = pose_answer(session, robot)
        pose = {**fresh, "robots": {**previous.pose["robots"], **fresh["robots"]}}
        held = {**previous.held, **session.slam.trajectory(robot)}
        alone = set(pose["robots"]) <= {robot}  # no other robot's pose to lag
        poses_log_id = session.last_log_id if alone else previous.poses_log_id
    if pipeline.off_graph_robots():
        held = None
    elif held is None:
        held = session.slam.trajectory()
    return MapView(
        map_id=session.record.id,
        log_id=session.last_log_id,
        summary=Summary().answer(session),
        pose=pose,
        places=None if pipeline.localiser is None else Places().answer(session),
        held=held,
        landmarks=Landmarks().answer(session) if landmarks else None,
        landmarks_log_id=session.last_log_id if landmarks else 0,
        poses_log_id=poses_log_id,
    )
