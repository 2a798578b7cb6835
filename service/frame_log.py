"""A map's frame log as its session uses it besides appending frames.

`FrameLog.complete` stores what one frame did (its result, events, removals, archived
landmarks and final trajectory rows, in one transaction); the estimator's sinks
collect the removals and rows during the frame. `FrameLog.load` rebuilds the map's
pipeline: the latest snapshot, then the log's tail replayed through the estimator. A
frame logged but never finished (the worker died handling it) is finished then, or,
after MAX_REPLAY_ATTEMPTS reloads that died on it too, dropped as a poison pill.
"""

from __future__ import annotations

import json
import logging
import pickle
import time
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import numpy as np

from frontend.errors import ImageError
from graph.errors import EstimationError, InvalidFrame
from graph.slam import BearingSlam, RemovalRecord
from graph.snapshot import SnapshotError
from graph.trajectory import PoseRow
from graph.types import FrameInput
from service.frame_results import frame_events, result_doc
from service.frames_io import frame_from_dict, frame_to_dict
from service.image_frames import MapVision
from service.pipeline import FrameStep, MapPipeline
from service.pipeline.config import slam_config
from service.pipeline.snapshot import fresh_pipeline, restore_pipeline
from service.store import MapPlace, MapRecord, StoredFrame
from service.store_sql import MapStore

log = logging.getLogger(__name__)

IMPORTED_FRONTEND = "imported_frontend"
"""Meta key: an imported camera map's front-end state and the log frame it follows."""
MAX_REPLAY_ATTEMPTS = 2
"""Reloads that may retry an unfinished log frame before it is dropped as a poison pill."""
_POSE_FLUSH = 4096
"""Final trajectory rows a reload collects before it writes them (bounds its memory)."""

T = TypeVar("T")


class _Buffer(Generic[T]):
    """Collects what the estimator's sinks hand out during one frame (removal records,
    final trajectory rows), to be stored with the frame's result."""

    def __init__(self) -> None:
        self.items: list[T] = []

    def append(self, item: T) -> None:
        self.items.append(item)

    def extend(self, items: list[T]) -> None:
        self.items.extend(items)

    def take(self) -> list[T]:
        items, self.items = self.items, []
        return items


@dataclass(frozen=True)
class LoadedMap:
    """A map's pipeline as `FrameLog.load` rebuilt it."""

    pipeline: MapPipeline
    last_log_id: int
    """Id of the last log frame the pipeline took."""
    replayed: int
    """Log frames replayed after the snapshot (frames since it)."""
    from_snapshot: int
    """Log id the snapshot covered (0: none, the whole log replayed)."""
    errors: int
    """Log frames that failed on replay (dropped, or acknowledged and skipped)."""


def _restore_imported_frontend(pipeline: MapPipeline, imported: Any, upto: int, last: int) -> None:
    """Replaying an imported map's log without a snapshot from after its import: put
    the export's front-end state back where the import did (after log frame `after`)."""
    if imported is None or pipeline.images is None:
        return
    after = int(imported["after"])
    if last == after and upto <= after:
        pipeline.images.set_state_doc(imported["state"])


class FrameLog:
    """One map's log: frames' completion and the map's reload. Not thread-safe."""

    def __init__(self, store: MapStore, place: MapPlace) -> None:
        self.store = store
        self._place = place
        self._removals: _Buffer[RemovalRecord] = _Buffer()
        self._poses: _Buffer[PoseRow] = _Buffer()
        self._removal_count: int | None = None

    def discard(self) -> None:
        """Drop what the estimator's sinks collected during a frame that failed."""
        self._removals.take()
        self._poses.take()

    def complete(
        self,
        slam: BearingSlam,
        log_id: int,
        result_json: str,
        step: FrameStep,
        observations: str | None = None,
    ) -> list[tuple[int, str, str]]:
        """Store the frame's result with its events, the removals and final trajectory
        rows the sinks collected, and archived landmarks (one transaction); the events
        as stored (id, kind, data)."""
        removals = self._removals.take()
        events, rows, archived = frame_events(slam, step, result_json, removals, log_id)
        restored = () if step.outcome is None else step.outcome.restored
        ids = self.store.complete_frame(
            log_id,
            result_json,
            events,
            rows,
            observations,
            self._poses.take(),
            archived=archived,
            restored=restored,
        )
        if self._removal_count is not None:
            self._removal_count += len(rows)
        return [(i, kind, data) for i, (kind, data) in zip(ids, events, strict=True)]

    def removal_count(self) -> int:
        """Rows of the map's removal log (counted once, then kept: a summary is
        published with every frame, and counting grows with the log)."""
        if self._removal_count is None:
            self._removal_count = self.store.removal_count()
        return self._removal_count

    # ------------------------------------------------------------ reload
    def load(self, record: MapRecord, vision: MapVision | None, *, seed: int) -> LoadedMap:
        """The map's pipeline: its latest snapshot + the log's tail. What the sinks
        collected before (a frame or an upkeep that failed on the map being replaced) is
        dropped first: it would otherwise be stored with the reload's rows."""
        t0 = time.perf_counter()
        self.discard()
        self._removal_count = None
        snap = self.store.latest_snapshot()
        pipeline, upto = None, 0
        frontend = None if vision is None else self.store.latest_frontend_state()
        if snap is not None and vision is not None and frontend is None:
            log.warning(
                "map %s: snapshot without front-end state, replaying the whole log", self._place
            )
            snap = None
        if snap is not None:
            try:
                pipeline = restore_pipeline(
                    snap[1],
                    frontend,
                    seed=seed,
                    front_end=None if vision is None else vision.front_end,
                    removal_sink=self._removals.append,
                    trajectory_sink=self._poses.extend,
                )
                pipeline.slam.config = slam_config(record.config, record.mode)
                upto = snap[0]
            except (SnapshotError, ValueError, pickle.UnpicklingError):
                log.exception("map %s: unreadable snapshot, replaying the whole log", self._place)
                pipeline, upto = None, 0
        if pipeline is None:
            pipeline = self._fresh(record, vision, seed)
        tail = self.store.frames_after(upto)
        last, errors = upto, 0
        imported = None if vision is None else self.store.get_meta(IMPORTED_FRONTEND)
        for stored in tail:
            _restore_imported_frontend(pipeline, imported, upto, last)
            if not self._replay(pipeline, stored, record.id, vision):
                errors += 1
            last = stored.id
            if len(self._poses.items) >= _POSE_FLUSH:
                self.store.put_poses(self._poses.take())
        _restore_imported_frontend(pipeline, imported, upto, last)
        # Rows the tail made final again (replaced: a restored estimator may round a
        # little differently from the one that first made them final).
        self.store.put_poses(self._poses.take())
        log.info(
            "map %s: loaded snapshot up to frame %d + %d log frames in %.0f ms",
            record.id,
            upto,
            len(tail),
            1e3 * (time.perf_counter() - t0),
        )
        return LoadedMap(pipeline, last, len(tail), upto, errors)

    def _fresh(self, record: MapRecord, vision: MapVision | None, seed: int) -> MapPipeline:
        slam = BearingSlam(
            slam_config(record.config, record.mode),
            rng=np.random.default_rng(seed),
            removal_sink=self._removals.append,
            trajectory_sink=self._poses.extend,
        )
        front_end = None if vision is None else vision.front_end
        return fresh_pipeline(slam, seed=seed, front_end=front_end)

    def _replay(
        self, pipeline: MapPipeline, stored: StoredFrame, map_id: str, vision: MapVision | None
    ) -> bool:
        """One log frame again (an unfinished one finished now); False when it failed."""
        if stored.result is None:
            # Logged but never finished: the process died while handling it. If that
            # happened on every reload as well, the frame itself kills the worker
            # (a poison pill): drop it instead of crashing forever.
            if stored.attempts >= MAX_REPLAY_ATTEMPTS:
                log.error(
                    "map %s: dropping log frame %d (robot %s seq %d): the worker died "
                    "%d times processing it",
                    map_id,
                    stored.id,
                    stored.robot,
                    stored.seq,
                    stored.attempts + 1,
                )
                self.store.delete_frame(stored.id)
                return False
            self.store.count_attempt(stored.id)
        doc = json.loads(stored.body)
        frame = frame_from_dict(doc)
        observations = None
        try:
            if "image" in doc:
                step, observations = self._replay_image(pipeline, stored.id, frame, vision)
            else:
                step = pipeline.step(frame)
        except (InvalidFrame, EstimationError, ImageError):
            self._removals.take()
            # The final rows collected so far stay for the load's flush: the estimator
            # goes on without them, whatever this frame did before it failed.
            if stored.result is None:  # never acknowledged: drop it
                log.warning("map %s: dropping unprocessable log frame %d", self._place, stored.id)
                self.store.delete_frame(stored.id)
            else:
                log.exception(
                    "map %s: acknowledged frame %d failed on replay", self._place, stored.id
                )
            return False
        if stored.result is None:  # appended but not completed before a crash
            result = result_doc(pipeline.slam, step, stored.id, {})
            self.complete(pipeline.slam, stored.id, json.dumps(result), step, observations)
        else:
            self._removals.take()
        return True

    def _replay_image(
        self, pipeline: MapPipeline, log_id: int, frame: FrameInput, vision: MapVision | None
    ) -> tuple[FrameStep, str | None]:
        """A logged image frame again: through the front end from its image, or (an
        imported frame, no image) from the observations its image gave. Returns the
        frame's step and the observations as JSON text (None for an imported frame)."""
        if vision is None:
            raise InvalidFrame("image", f"log frame {log_id}: the map has no camera")
        image = self.store.frame_image(log_id)
        if image is None:
            observations = self.store.image_observations(log_id)
            if observations is None:
                raise InvalidFrame("image", f"log frame {log_id}: image and observations missing")
            observed = frame_from_dict({**frame_to_dict(frame), "observations": observations})
            return pipeline.step(observed, landmark_covariances=False), None
        step, as_json, _ = vision.step(pipeline, frame, image)
        return step, as_json
