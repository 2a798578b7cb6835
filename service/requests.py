"""What the API process asks of a map's worker: one frozen dataclass per operation.

A request carries its arguments; its type names the operation and, as its type
parameter, the type of the answer, so ``await engine.call(map_id, Pose())`` is typed
end to end. A `MapRequest` answers from the map's open session (`answer`); a
`WorkerRequest` (ping, create, open, delete, import) works on the worker's set of
maps and is carried out by service.worker. Requests cross the process boundary
pickled (a local worker's pipe, or a Ray actor call).

Adding a query: a `MapRequest` here whose `answer` calls the query (service.queries),
and the route that asks it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

from service import queries
from service.exchange import export_map
from service.frame_results import FrameReply
from service.pipeline.config import Mode
from service.session import MapSession

T = TypeVar("T", covariant=True)

Doc = dict[str, Any]
"""A JSON document (the REST response models describe and check its members)."""


class Request(Generic[T]):
    """Anything the API process sends a worker; its answer is a `T`."""


class MapRequest(Request[T]):
    """An operation on one open map, answered from its session."""

    def answer(self, session: MapSession) -> T:
        raise NotImplementedError


class WorkerRequest(Request[T]):
    """An operation on the worker's set of maps (service.worker carries it out)."""


# ------------------------------------------------------------ the worker's maps
@dataclass(frozen=True)
class Ping(WorkerRequest[Doc]):
    """The worker's process id and the maps it has open."""


@dataclass(frozen=True)
class CreateMap(WorkerRequest[Doc]):
    """A new, empty map of `record` (a MapRecord's dict); its summary."""

    record: Doc


@dataclass(frozen=True)
class OpenMap(WorkerRequest[Doc]):
    """Open the map (snapshot + log tail) if it is not open; its frame count."""


@dataclass(frozen=True)
class DeleteMap(WorkerRequest[None]):
    """Close the map and remove its store."""


@dataclass(frozen=True)
class ImportMap(WorkerRequest[Doc]):
    """A new map from an export document's bytes: {"record", "summary"}."""

    body: bytes
    created: float
    default_cap: int | None


# ------------------------------------------------------------ one map
@dataclass(frozen=True)
class SubmitFrame(MapRequest[FrameReply]):
    """One frame object (with `image`: an image frame's meta and its bytes)."""

    frame: Doc
    image: bytes | None = None

    def answer(self, session: MapSession) -> FrameReply:
        return session.submit(self.frame, self.image)


@dataclass(frozen=True)
class Summary(MapRequest[Doc]):
    """The map's record, estimator parameters, counts, robots and frame timings."""

    def answer(self, session: MapSession) -> Doc:
        return queries.summary(session)


@dataclass(frozen=True)
class SetMode(MapRequest[Doc]):
    """Switch between mapping and localisation; the map's summary."""

    mode: Mode

    def answer(self, session: MapSession) -> Doc:
        session.set_mode(self.mode)
        return queries.summary(session)


@dataclass(frozen=True)
class Pose(MapRequest[Doc]):
    """The latest pose of each robot (service.queries.pose)."""

    def answer(self, session: MapSession) -> Doc:
        return queries.pose(session)


@dataclass(frozen=True)
class Trajectory(MapRequest[dict[str, list[Doc]]]):
    """Poses per robot (service.queries.trajectory)."""

    robot: str | None = None
    stats_every: int = 0

    def answer(self, session: MapSession) -> dict[str, list[Doc]]:
        return queries.trajectory(session, self.robot, stats_every=self.stats_every)


@dataclass(frozen=True)
class Landmarks(MapRequest[list[Doc]]):
    """The live landmarks, or (`state` "archived") those in the archive."""

    state: str = "live"

    def answer(self, session: MapSession) -> list[Doc]:
        return queries.landmarks(session, self.state)


@dataclass(frozen=True)
class Coverage(MapRequest[Doc]):
    """The coverage grid (service.queries.coverage)."""

    cell_m: float
    radius_m: float
    removals: int

    def answer(self, session: MapSession) -> Doc:
        return queries.coverage(
            session, cell_m=self.cell_m, radius_m=self.radius_m, removals=self.removals
        )


@dataclass(frozen=True)
class Places(MapRequest[Doc]):
    """Learnt places and the transitions between them."""

    def answer(self, session: MapSession) -> Doc:
        return queries.places(session)


@dataclass(frozen=True)
class LearnPlace(MapRequest[Doc]):
    """Learn a place at a robot's current pose (default: the last robot seen)."""

    robot: str | None = None

    def answer(self, session: MapSession) -> Doc:
        return queries.learn_place(session, self.robot)


@dataclass(frozen=True)
class Export(MapRequest[bytes]):
    """The map's export document as compact JSON bytes (serialised in the worker)."""

    def answer(self, session: MapSession) -> bytes:
        return json.dumps(export_map(session), separators=(",", ":")).encode()
