"""What the API process asks of a map's worker: one frozen dataclass per operation.

A request carries its arguments; its type names the operation and, as its type
parameter, the type of the answer, so ``await engine.call(map_id, Pose())`` is typed
end to end. A `MapRequest` answers from the map's open session (`answer`); a
`WorkerRequest` (ping, create, open, close, delete, import) works on the worker's set of
maps and is carried out by service.worker. Requests cross the process boundary
pickled (a local worker's pipe, or a Ray actor call).

The queries are in service.queries, the export in service.exchange: adding a query is a
`MapRequest` there and the route that asks it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Generic, TypeVar

from service.frame_results import FrameReply
from service.session import MapSession

if TYPE_CHECKING:
    from service.published import MapView
    from service.store import Store

T = TypeVar("T", covariant=True)

Doc = dict[str, Any]
"""A JSON document (the REST response models describe and check its members)."""


class Request(Generic[T]):
    """Anything the API process sends a worker; its answer is a `T`."""


class MapRequest(Request[T]):
    """An operation on one open map, answered from its session."""

    view_reads_store: ClassVar[bool] = False
    """`from_view` reads the store (the API process calls it in a thread)."""

    def answer(self, session: MapSession) -> T:
        raise NotImplementedError

    def from_view(self, view: MapView, store: Store) -> T | None:
        """The answer from the map's published view (service.published) and the store
        (read only, may block), in the API process; None: only the worker can answer."""
        return None

    def view_behind(self, view: MapView) -> bool:
        """The view's answer lags behind the map (the worker's is exact)."""
        return False


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
class RefreshView(WorkerRequest[None]):
    """Publish the map's view with its live landmarks and held trajectory rows computed
    now (a read found the published ones behind the map)."""

    whole: bool = False
    """Send the whole view (the API process has none the next delta could apply to)."""


@dataclass(frozen=True)
class CloseMap(WorkerRequest[None]):
    """Snapshot the map if frames came since its last snapshot and close it (it moves to
    another worker, which opens it from that snapshot)."""


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
    """One frame object (with `image`: an image frame's meta and its bytes). A worker
    checks it against its settings' frame limits as it parses it (service.worker)."""

    frame: Doc
    image: bytes | None = None

    def answer(self, session: MapSession) -> FrameReply:
        return session.submit(self.frame, self.image)
