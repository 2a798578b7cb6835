"""MapSession: one map's pipeline around `BearingSlam`, with its durable log.

A session lives in the worker process that owns the map. `submit` is the frame
use case: parse, idempotency check, order check, append to the log (committed),
process, store the result with its events and removals, snapshot periodically.
`MapSession.open` rebuilds a map from its database: the latest snapshot, then
the log's tail replayed through the estimator.
"""

from __future__ import annotations

import json
import logging
import pickle
import time
from collections import deque
from pathlib import Path
from typing import Any, Generic, TypeVar

import numpy as np

from frontend.errors import ImageError
from graph.errors import EstimationError, InvalidFrame, OutOfOrderFrame
from graph.slam import BearingSlam, RemovalRecord
from graph.snapshot import SnapshotError
from graph.trajectory import PoseRow
from graph.types import FrameInput
from graph.validation import validate_frame
from service.errors import ServiceError, invalid_frame, out_of_order
from service.frame_model import FrameLimits
from service.frame_results import FrameReply, frame_events, result_doc
from service.frames_io import (
    canonical_frame,
    frame_from_dict,
    frame_to_dict,
    image_record,
    observations_json,
)
from service.image_frames import MapVision, Pending, image_refused, no_camera
from service.pipeline import FrameStep, ImageFeatures, MapPipeline
from service.pipeline.config import MapConfig, slam_config
from service.pipeline.snapshot import fresh_pipeline, restore_pipeline, snapshot_pipeline
from service.settings import StoreSettings
from service.store import MapPlace, MapRecord, StoredFrame, as_place
from service.store_sql import MapStore

log = logging.getLogger(__name__)

SNAPSHOT_OVERDUE = 5
"""A snapshot due for this many times `snapshot_every` frames is taken inside a request."""
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


def _restore_imported_frontend(pipeline: MapPipeline, imported: Any, upto: int, last: int) -> None:
    """Replaying an imported map's log without a snapshot from after its import: put
    the export's front-end state back where the import did (after log frame `after`)."""
    if imported is None or pipeline.images is None:
        return
    after = int(imported["after"])
    if last == after and upto <= after:
        pipeline.images.set_state_doc(imported["state"])


class MapSession:
    """One map: estimator + store. Not thread-safe; one worker process calls it."""

    def __init__(self, where: Path | MapPlace, settings: StoreSettings) -> None:
        """The map stored at `where`: a SQLite file, or a place in any store."""
        self.place = as_place(where, synchronous=settings.synchronous)
        self._settings = settings
        self.store: MapStore = self.place.open()
        meta = self.store.get_meta("record")
        if meta is None:
            self.store.close()
            raise ServiceError(
                500, "corrupt-map", "Map store incomplete", f"{self.place} has no map record"
            )
        self.record = MapRecord.from_dict(meta)
        self._removals: _Buffer[RemovalRecord] = _Buffer()
        self._poses: _Buffer[PoseRow] = _Buffer()
        self._timing: deque[float] = deque(maxlen=1000)
        self.replay_errors = 0
        self.loaded_from_snapshot = 0
        """Log id the snapshot used at the last load covered (0: none, whole log replayed)."""
        self._removal_count: int | None = None
        self.vision = MapVision.for_config(self.record.config)
        """The front end of a map with a camera (image frames); None without one."""
        self.pipeline, self._last_log_id, self._since_snapshot = self._load()

    # ------------------------------------------------------------ lifecycle
    @classmethod
    def create(
        cls, where: Path | MapPlace, record: MapRecord, settings: StoreSettings
    ) -> MapSession:
        """A new, empty map (an orphaned store of the same place is replaced)."""
        slam_config(record.config, record.mode)  # refuse a bad config before writing anything
        place = as_place(where, synchronous=settings.synchronous)
        place.remove()
        store = place.open()
        store.set_meta("record", record.as_dict())
        store.close()
        return cls(place, settings)

    def close(self) -> None:
        if self.vision is not None:
            self.vision.close()
        self.store.close()

    @property
    def slam(self) -> BearingSlam:
        """The map's estimator."""
        return self.pipeline.slam

    @property
    def last_log_id(self) -> int:
        """Id of the last frame in the map's log that the pipeline took."""
        return self._last_log_id

    def _fresh(self) -> MapPipeline:
        config = slam_config(self.record.config, self.record.mode)
        slam = BearingSlam(
            config,
            rng=np.random.default_rng(self.seed()),
            removal_sink=self._removals.append,
            trajectory_sink=self._poses.extend,
        )
        front_end = None if self.vision is None else self.vision.front_end
        return fresh_pipeline(slam, seed=self.seed(), front_end=front_end)

    def _load(self) -> tuple[MapPipeline, int, int]:
        """Latest snapshot + the log's tail: (pipeline, last log id, frames since
        snapshot)."""
        t0 = time.perf_counter()
        snap = self.store.latest_snapshot()
        pipeline, upto = None, 0
        frontend = None if self.vision is None else self.store.latest_frontend_state()
        if snap is not None and self.vision is not None and frontend is None:
            log.warning(
                "map %s: snapshot without front-end state, replaying the whole log", self.place
            )
            snap = None
        if snap is not None:
            try:
                pipeline = restore_pipeline(
                    snap[1],
                    frontend,
                    seed=self.seed(),
                    front_end=None if self.vision is None else self.vision.front_end,
                    removal_sink=self._removals.append,
                    trajectory_sink=self._poses.extend,
                )
                pipeline.slam.config = slam_config(self.record.config, self.record.mode)
                upto = snap[0]
            except (SnapshotError, ValueError, pickle.UnpicklingError):
                log.exception("map %s: unreadable snapshot, replaying the whole log", self.place)
                pipeline, upto = None, 0
        if pipeline is None:
            pipeline = self._fresh()
        tail = self.store.frames_after(upto)
        self.loaded_from_snapshot = upto
        last = upto
        imported = None if self.vision is None else self.store.get_meta(IMPORTED_FRONTEND)
        for stored in tail:
            _restore_imported_frontend(pipeline, imported, upto, last)
            self._replay(pipeline, stored)
            last = stored.id
            if len(self._poses.items) >= _POSE_FLUSH:
                self.store.put_poses(self._poses.take())
        _restore_imported_frontend(pipeline, imported, upto, last)
        # Rows the tail made final again (replaced: a restored estimator may round a
        # little differently from the one that first made them final).
        self.store.put_poses(self._poses.take())
        log.info(
            "map %s: loaded snapshot up to frame %d + %d log frames in %.0f ms",
            self.record.id,
            upto,
            len(tail),
            1e3 * (time.perf_counter() - t0),
        )
        return pipeline, last, len(tail)

    def _replay(self, pipeline: MapPipeline, stored: StoredFrame) -> None:
        if stored.result is None:
            # Logged but never finished: the process died while handling it. If that
            # happened on every reload as well, the frame itself kills the worker
            # (a poison pill): drop it instead of crashing forever.
            if stored.attempts >= MAX_REPLAY_ATTEMPTS:
                log.error(
                    "map %s: dropping log frame %d (robot %s seq %d): the worker died "
                    "%d times processing it",
                    self.record.id,
                    stored.id,
                    stored.robot,
                    stored.seq,
                    stored.attempts + 1,
                )
                self.replay_errors += 1
                self.store.delete_frame(stored.id)
                return
            self.store.count_attempt(stored.id)
        doc = json.loads(stored.body)
        frame = frame_from_dict(doc)
        observations = None
        try:
            if "image" in doc:
                step, observations = self._replay_image(pipeline, stored.id, frame)
            else:
                step = pipeline.step(frame)
        except (InvalidFrame, EstimationError, ImageError):
            self.replay_errors += 1
            self._removals.take()
            # The final rows collected so far stay for the load's flush: the estimator
            # goes on without them, whatever this frame did before it failed.
            if stored.result is None:  # never acknowledged: drop it
                log.warning("map %s: dropping unprocessable log frame %d", self.place, stored.id)
                self.store.delete_frame(stored.id)
            else:
                log.exception(
                    "map %s: acknowledged frame %d failed on replay", self.place, stored.id
                )
            return
        removals = self._removals.take()
        if stored.result is None:  # appended but not completed before a crash
            result = result_doc(pipeline.slam, step, stored.id, {})
            self._complete(
                pipeline.slam,
                stored.id,
                json.dumps(result),
                step,
                removals,
                observations,
                self._poses.take(),
            )

    def _replay_image(
        self, pipeline: MapPipeline, log_id: int, frame: FrameInput
    ) -> tuple[FrameStep, str | None]:
        """A logged image frame again: through the front end from its image, or (an
        imported frame, no image) from the observations its image gave. Returns the
        frame's step and the observations as JSON text (None for an imported frame)."""
        if self.vision is None:
            raise InvalidFrame("image", f"log frame {log_id}: the map has no camera")
        image = self.store.frame_image(log_id)
        if image is None:
            observations = self.store.image_observations(log_id)
            if observations is None:
                raise InvalidFrame("image", f"log frame {log_id}: image and observations missing")
            observed = frame_from_dict({**frame_to_dict(frame), "observations": observations})
            return pipeline.step(observed, landmark_covariances=False), None
        features, sig, _ = self.vision.features_of(image)
        step = pipeline.step(frame, image=ImageFeatures(features, sig))
        return step, observations_json(step.observations)

    @property
    def snapshot_due(self) -> bool:
        """Enough frames since the last snapshot: take one when the worker is idle.

        A snapshot of a 150-variable graph takes ~0.2 s (GTSAM's text serialisation of
        the marginal factors), so the worker takes it between requests, not inside one.
        """
        return self._since_snapshot >= self._settings.snapshot_every

    @property
    def unsnapshotted(self) -> bool:
        """Frames came since the last snapshot (a reload would replay them)."""
        return self._since_snapshot > 0

    def _count_frame(self) -> None:
        self._since_snapshot += 1
        if self._since_snapshot >= SNAPSHOT_OVERDUE * self._settings.snapshot_every:
            self.snapshot()  # never idle (a continuous stream): bound the replay anyway

    def snapshot(self) -> None:
        blob, frontend = snapshot_pipeline(self.pipeline)
        self.store.save_snapshot(
            self._last_log_id,
            blob,
            keep=self._settings.snapshots_kept,
            frontend=frontend,
            prune_images=self._settings.prune_images,
        )
        self.store.prune_events(self._settings.events_kept)
        self._since_snapshot = 0

    def set_mode(self, mode: str) -> None:
        self.record = MapRecord(
            self.record.id, self.record.name, mode, self.record.config, self.record.created
        )
        self.store.set_meta("record", self.record.as_dict())
        self.slam.config = slam_config(self.record.config, mode)

    # ------------------------------------------------------------ the frame use case
    def submit(
        self,
        body: dict[str, Any],
        image: bytes | None = None,
        *,
        imported: bool = False,
        limits: FrameLimits | None = None,
    ) -> FrameReply:
        """Take one frame object (with `image`: the meta of an image frame and its bytes).

        `imported`: `body` is an image frame of an export document: the image's digest
        (``"image"``) and the observations the front end made of it, which go to the
        estimator as they are. `limits`: a posted frame, checked against them too
        (service.frames_io.canonical_frame).

        Returns the frame result as stored (an idempotent retry: as stored before) with
        what the runtime reports of it (service.frame_results.FrameReply).
        """
        t0 = time.perf_counter()
        prefetched = None if self.vision is None or image is None else self.vision.take(image)
        digest = image_record(body.get("image"), "image") if imported else None
        frame, text = canonical_frame(body, image, digest, limits=limits)
        if image is not None:
            self._check_image_frame(frame)
        if imported and self.vision is None:
            raise no_camera(self.record.id)
        stored = self.store.find_frame(frame.robot, frame.seq)
        if stored is not None:
            if stored.body == text and stored.result is not None:
                return FrameReply(stored.result, replayed=True)
            raise ServiceError(
                409,
                "duplicate-seq",
                "Duplicate frame",
                f"seq: robot {frame.robot!r} already sent a different frame with seq "
                f"{frame.seq}; a retry must repeat the frame exactly",
                field="seq",
            )
        pending = None
        if self.vision is not None and image is not None:
            pending = prefetched or self.vision.extract(image)
        last = self.pipeline.last_accepted().get(frame.robot)
        try:
            validate_frame(
                frame,
                last_seq=None if last is None else last[0],
                last_stamp=None if last is None else last[1],
                require_initial_pose=False,
            )
        except OutOfOrderFrame as exc:
            raise out_of_order(exc.field, exc.detail) from exc
        except InvalidFrame as exc:
            raise invalid_frame(exc.field, exc.detail) from exc
        observations = observations_json(frame.observations) if imported else None
        log_id = self.store.append_frame(frame.robot, frame.seq, text, image, observations)
        t1 = time.perf_counter()
        vision_ms: dict[str, float] = {}
        try:
            if pending is None:
                step = self.pipeline.step(frame, landmark_covariances=not imported)
            else:
                step, observations, vision_ms = self._process_image(frame, pending)
        except ImageError as exc:
            self.store.delete_frame(log_id)
            raise image_refused(exc) from exc
        except InvalidFrame as exc:
            self.store.delete_frame(log_id)
            self._removals.take()
            self._poses.take()
            raise invalid_frame(exc.field, exc.detail) from exc
        except EstimationError as exc:
            self._forget_frame(log_id)
            raise ServiceError(
                422,
                "estimation-failed",
                "Estimation failed",
                f"the estimator could not take this frame ({exc}); the map is as before",
            ) from exc
        except Exception:
            # A bug of ours, half way through the frame (the caller gets a 500).
            self._forget_frame(log_id)
            raise
        removals = self._removals.take()
        final = step.outcome
        result = result_doc(self.slam, step, log_id, {"log": 1e3 * (t1 - t0), **vision_ms})
        t2 = time.perf_counter()
        text = json.dumps(result)
        events = self._complete(
            self.slam,
            log_id,
            text,
            step,
            removals,
            None if imported else observations,
            self._poses.take(),
        )
        store_ms = 1e3 * (time.perf_counter() - t2)
        self._last_log_id = log_id
        self._timing.append(1e3 * (time.perf_counter() - t0))
        self._count_frame()
        return FrameReply(
            text,
            events=events,
            timing_ms=result["timing_ms"],
            store_ms=store_ms,
            live=len(self.slam.landmarks),
            marginalised=0 if final is None else len(final.marginalised),
        )

    def _forget_frame(self, log_id: int) -> None:
        """Undo a frame the estimator failed on half way: the in-memory map may be half
        updated. The frame was never acknowledged; it leaves the log and the map is
        reloaded as it was, so that the next frame meets a whole map."""
        self.store.delete_frame(log_id)
        self._removals.take()
        self._poses.take()
        self._removal_count = None
        self.pipeline, self._last_log_id, self._since_snapshot = self._load()

    def _check_image_frame(self, frame: Any) -> None:
        if self.vision is None:
            raise no_camera(self.record.id)
        try:
            self.vision.check(frame)
            known = frame.robot in self.pipeline.last_accepted()
            self.vision.check_localisable(frame, known=known)
        except InvalidFrame as exc:
            raise invalid_frame(exc.field, exc.detail) from exc

    def _process_image(
        self, frame: Any, pending: Pending
    ) -> tuple[FrameStep, str, dict[str, float]]:
        """(the frame's step, the observations it is recorded with as JSON text, the
        front end's timings ms)."""
        assert self.vision is not None
        features, sig, timing = self.vision.features_of(pending)
        step = self.pipeline.step(frame, image=ImageFeatures(features, sig))
        return step, observations_json(step.observations), timing

    def _complete(
        self,
        slam: BearingSlam,
        log_id: int,
        result_json: str,
        step: FrameStep,
        removals: list[RemovalRecord],
        observations: str | None = None,
        poses: list[PoseRow] | None = None,
    ) -> list[tuple[int, str, str]]:
        """Store the frame's result with its events, removals, archived landmarks and
        final trajectory rows (one transaction); the events as stored (id, kind, data)."""
        events, rows, archived = frame_events(slam, step, result_json, removals, log_id)
        restored = () if step.outcome is None else step.outcome.restored
        ids = self.store.complete_frame(
            log_id,
            result_json,
            events,
            rows,
            observations,
            poses,
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

    def seed(self) -> int:
        """The map's seed (its config's)."""
        return MapConfig.model_validate(self.record.config).seed

    def frame_ms(self) -> np.ndarray:
        """(N,) processing time of the last (up to 1000) frames this session took, ms."""
        return np.fromiter(self._timing, dtype=np.float64, count=len(self._timing))
