"""MapSession: one map's pipeline around `BearingSlam`, with its durable log.

A session lives in the worker process that owns the map. `submit` is the frame
use case: parse, idempotency check, order check, append to the log (committed),
process, store the result with its events and removals, snapshot periodically.
Opening a session rebuilds the map from its store: the latest snapshot, then the
log's tail replayed through the estimator (service.frame_log).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from frontend.errors import ImageError
from graph.config import SlamConfig
from graph.errors import EstimationError, InvalidFrame, OutOfOrderFrame
from graph.slam import BearingSlam
from graph.types import FrameInput
from graph.validation import validate_frame
from service.errors import ServiceError, invalid_frame, out_of_order
from service.frame_log import FrameLog
from service.frame_model import FrameLimits
from service.frame_results import FrameReply, result_doc
from service.frames_io import canonical_frame, image_record, observations_json
from service.image_frames import MapVision, Pending, image_refused, no_camera
from service.pipeline import FrameStep
from service.pipeline.config import MapConfig, slam_config, slam_config_dict
from service.pipeline.snapshot import snapshot_pipeline
from service.settings import StoreSettings
from service.store import MapPlace, MapRecord, as_place
from service.store_sql import MapStore

log = logging.getLogger(__name__)

FRAME_TIMES = 1000
"""Frames whose processing times a session keeps (the summary's timing statistics)."""

SNAPSHOT_OVERDUE = 5
"""A snapshot due for this many times `snapshot_every` frames is taken inside a request."""


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
        self.frame_log = FrameLog(self.store, self.place)
        """Frames' completion and the map's reload (service.frame_log)."""
        self._timing = np.empty(FRAME_TIMES)
        """Processing times of the last FRAME_TIMES frames, ms, a ring (the summary published
        with every frame reads them all: an array, not a deque turned into one)."""
        self._timed = 0
        """Frames timed in all (the next one goes to `_timing[_timed % FRAME_TIMES]`)."""
        self._estimator: tuple[SlamConfig, dict[str, Any]] | None = None
        self.replay_errors = 0
        """Log frames that failed on replay at the loads so far."""
        self.loaded_from_snapshot = 0
        """Log id the snapshot used at the last load covered (0: none, whole log replayed)."""
        self.vision = MapVision.for_config(self.record.config)
        """The front end of a map with a camera (image frames); None without one."""
        self._load()

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

    def _load(self) -> None:
        """(Re)build the pipeline from the map's latest snapshot and its log's tail."""
        loaded = self.frame_log.load(self.record, self.vision, seed=self.seed())
        self.pipeline = loaded.pipeline
        self._last_log_id = loaded.last_log_id
        self._since_snapshot = loaded.replayed
        self.loaded_from_snapshot = loaded.from_snapshot
        self.replay_errors += loaded.errors

    @property
    def snapshot_due(self) -> bool:
        """Enough frames since the last snapshot: take one when the worker is idle (a
        snapshot serialises the whole graph: between requests, not inside one)."""
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
        self.record = dataclasses.replace(self.record, mode=mode)
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
        retry = self._retry_of(frame, text)
        if retry is not None:
            return retry
        pending = None
        if self.vision is not None and image is not None:
            pending = prefetched or self.vision.extract(image)
        self._check_order(frame)
        observations = observations_json(frame.observations) if imported else None
        log_id = self.store.append_frame(frame.robot, frame.seq, text, image, observations)
        t1 = time.perf_counter()
        step, observed, vision_ms = self._step(frame, log_id, pending, imported=imported)
        final = step.outcome
        result = result_doc(self.slam, step, log_id, {"log": 1e3 * (t1 - t0), **vision_ms})
        t2 = time.perf_counter()
        text = json.dumps(result)
        events = self.frame_log.complete(self.slam, log_id, text, step, observed)
        store_ms = 1e3 * (time.perf_counter() - t2)
        self._last_log_id = log_id
        self._timing[self._timed % FRAME_TIMES] = 1e3 * (time.perf_counter() - t0)
        self._timed += 1
        self._count_frame()
        return FrameReply(
            text,
            events=events,
            timing_ms=result["timing_ms"],
            store_ms=store_ms,
            live=len(self.slam.landmarks),
            marginalised=0 if final is None else len(final.marginalised),
        )

    def upkeep(self) -> bool:
        """The estimator's work the last frame left for after its result was sent
        (SlamConfig.upkeep after the frame): the worker calls it before its next request.
        What it removes is stored, sent and published with the next frame's result; a
        snapshot meanwhile keeps it pending. If it fails, the map is reloaded from its
        store (the log's frames replayed) and this upkeep is skipped: the next frame's
        upkeep brings the map back under its cap. Whether there was one (the map
        changed)."""
        if not self.slam.upkeep_pending:
            return False
        try:
            self.pipeline.upkeep()
        except EstimationError:
            log.exception(
                "map %s: the upkeep after log frame %d failed", self.place, self._last_log_id
            )
            self._load()
            self.slam.skip_upkeep()
        return True

    def _retry_of(self, frame: FrameInput, text: str) -> FrameReply | None:
        """The stored answer when the frame repeats a logged one exactly (an idempotent
        retry); None for a new frame; 409 for a different frame with a logged seq."""
        stored = self.store.find_frame(frame.robot, frame.seq)
        if stored is None:
            return None
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

    def _check_order(self, frame: FrameInput) -> None:
        """Refuse a frame that does not follow its robot's last one (409) or is invalid
        (422)."""
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

    def _step(
        self, frame: FrameInput, log_id: int, pending: Pending | None, *, imported: bool
    ) -> tuple[FrameStep, str | None, dict[str, float]]:
        """The logged frame `log_id` through the pipeline (an image frame's features from
        `pending`): (its step, the observations its image gave as JSON text, the front
        end's timings ms). A refusal takes the frame out of the log again and leaves the
        map as it was."""
        try:
            if pending is None:
                return self.pipeline.step(frame, landmark_covariances=not imported), None, {}
            assert self.vision is not None
            return self.vision.step(self.pipeline, frame, pending)
        except ImageError as exc:
            self.store.delete_frame(log_id)
            raise image_refused(exc) from exc
        except InvalidFrame as exc:
            self.store.delete_frame(log_id)
            self.frame_log.discard()
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

    def _forget_frame(self, log_id: int) -> None:
        """Undo a frame the estimator failed on half way: the in-memory map may be half
        updated. The frame was never acknowledged; it leaves the log and the map is
        reloaded as it was, so that the next frame meets a whole map."""
        self.store.delete_frame(log_id)
        self._load()

    def _check_image_frame(self, frame: FrameInput) -> None:
        if self.vision is None:
            raise no_camera(self.record.id)
        try:
            self.vision.check(frame)
            known = frame.robot in self.pipeline.last_accepted()
            self.vision.check_localisable(frame, known=known)
        except InvalidFrame as exc:
            raise invalid_frame(exc.field, exc.detail) from exc

    def removal_count(self) -> int:
        """Rows of the map's removal log."""
        return self.frame_log.removal_count()

    def seed(self) -> int:
        """The map's seed (its config's)."""
        return MapConfig.model_validate(self.record.config).seed

    def frame_ms(self) -> np.ndarray:
        """(N,) processing time of the last (up to FRAME_TIMES) frames this session took,
        ms, oldest first."""
        if self._timed <= FRAME_TIMES:
            return self._timing[: self._timed].copy()
        start = self._timed % FRAME_TIMES
        return np.concatenate((self._timing[start:], self._timing[:start]))

    def estimator_doc(self) -> dict[str, Any]:
        """Every parameter of the map's estimator by name (slam_config_dict), made once
        per config (a summary is published with every frame); not to be changed."""
        config = self.slam.config
        if self._estimator is None or self._estimator[0] is not config:
            self._estimator = (config, slam_config_dict(config))
        return self._estimator[1]
