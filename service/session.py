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
import shutil
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from graph.errors import EstimationError, InvalidFrame, OutOfOrderFrame
from graph.slam import BearingSlam, FrameOutcome, RemovalRecord
from graph.snapshot import SnapshotError, capture, last_accepted, restore
from graph.validation import validate_frame
from service.errors import ServiceError, invalid_frame, out_of_order
from service.exchange import EXPORT_FORMAT, EXPORT_VERSION
from service.frames_io import frame_from_dict, frame_to_dict
from service.mapconfig import MapConfig, slam_config, slam_config_dict
from service.settings import StoreSettings
from service.store import MapRecord, MapStore, StoredFrame
from service.views import (
    attach_frame_stats,
    coverage_doc,
    landmarks_doc,
    pose_doc,
    trajectory_doc,
)

log = logging.getLogger(__name__)

SNAPSHOT_OVERDUE = 5
"""A snapshot due for this many times `snapshot_every` frames is taken inside a request."""
MAX_REPLAY_ATTEMPTS = 2
"""Reloads that may retry an unfinished log frame before it is dropped as a poison pill."""


def canonical_frame(body: dict[str, Any]) -> tuple[Any, str]:
    """Parse a frame object; (FrameInput, canonical JSON text used for idempotency)."""
    try:
        frame = frame_from_dict(body)
    except InvalidFrame as exc:
        raise invalid_frame(exc.field, exc.detail) from exc
    text = json.dumps(frame_to_dict(frame), sort_keys=True, separators=(",", ":"))
    return frame, text


class _RemovalBuffer:
    """Collects the removals of one frame (the estimator's removal sink)."""

    def __init__(self) -> None:
        self.items: list[RemovalRecord] = []

    def __call__(self, record: RemovalRecord) -> None:
        self.items.append(record)

    def take(self) -> list[RemovalRecord]:
        items, self.items = self.items, []
        return items


def remove_map_files(path: Path) -> None:
    """Delete a map's database and its WAL/SHM companions."""
    for suffix in ("", "-wal", "-shm"):
        p = Path(str(path) + suffix)
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()


class MapSession:
    """One map: estimator + store. Not thread-safe; one worker process calls it."""

    def __init__(self, path: Path, settings: StoreSettings) -> None:
        self.path = path
        self._settings = settings
        self.store = MapStore(path, synchronous=settings.synchronous)
        meta = self.store.get_meta("record")
        if meta is None:
            self.store.close()
            raise ServiceError(
                500, "corrupt-map", "Map store incomplete", f"{path.name} has no map record"
            )
        self.record = MapRecord.from_dict(meta)
        self._removals = _RemovalBuffer()
        self._timing: deque[float] = deque(maxlen=1000)
        self.replay_errors = 0
        self.loaded_from_snapshot = 0
        """Log id the snapshot used at the last load covered (0: none, whole log replayed)."""
        self.slam, self._last_log_id, self._since_snapshot = self._load()

    # ------------------------------------------------------------ lifecycle
    @classmethod
    def create(cls, path: Path, record: MapRecord, settings: StoreSettings) -> MapSession:
        """A new, empty map (an orphaned file of the same id is replaced)."""
        slam_config(record.config, record.mode)  # refuse a bad config before writing anything
        remove_map_files(path)
        store = MapStore(path, synchronous=settings.synchronous)
        store.set_meta("record", record.as_dict())
        store.close()
        return cls(path, settings)

    def close(self) -> None:
        self.store.close()

    def _fresh(self) -> BearingSlam:
        config = slam_config(self.record.config, self.record.mode)
        seed = MapConfig.model_validate(self.record.config).seed
        return BearingSlam(config, rng=np.random.default_rng(seed), removal_sink=self._removals)

    def _load(self) -> tuple[BearingSlam, int, int]:
        """Latest snapshot + the log's tail: (estimator, last log id, frames since snapshot)."""
        t0 = time.perf_counter()
        snap = self.store.latest_snapshot()
        slam, upto = self._fresh(), 0
        if snap is not None:
            try:
                slam = restore(snap[1], removal_sink=self._removals)
                slam.config = slam_config(self.record.config, self.record.mode)
                upto = snap[0]
            except SnapshotError:
                log.exception("map %s: unreadable snapshot, replaying the whole log", self.path)
                slam, upto = self._fresh(), 0
        tail = self.store.frames_after(upto)
        self.loaded_from_snapshot = upto
        last = upto
        for stored in tail:
            self._replay(slam, stored)
            last = stored.id
        log.info(
            "map %s: loaded snapshot up to frame %d + %d log frames in %.0f ms",
            self.record.id,
            upto,
            len(tail),
            1e3 * (time.perf_counter() - t0),
        )
        return slam, last, len(tail)

    def _replay(self, slam: BearingSlam, stored: StoredFrame) -> None:
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
        frame = frame_from_dict(json.loads(stored.body))
        try:
            outcome = slam.process(frame, with_covariance=stored.result is None)
        except (InvalidFrame, EstimationError):
            self.replay_errors += 1
            self._removals.take()
            if stored.result is None:  # never acknowledged: drop it
                log.warning("map %s: dropping unprocessable log frame %d", self.path, stored.id)
                self.store.delete_frame(stored.id)
            else:
                log.exception(
                    "map %s: acknowledged frame %d failed on replay", self.path, stored.id
                )
            return
        removals = self._removals.take()
        if stored.result is None:  # appended but not completed before a crash
            result = self._result_doc(slam, outcome, stored.id, {})
            self._complete(slam, stored.id, json.dumps(result), outcome, removals)

    @property
    def snapshot_due(self) -> bool:
        """Enough frames since the last snapshot: take one when the worker is idle.

        A snapshot of a 150-variable graph takes ~0.2 s (GTSAM's text serialisation of
        the marginal factors), so the worker takes it between requests, not inside one.
        """
        return self._since_snapshot >= self._settings.snapshot_every

    def _count_frame(self) -> None:
        self._since_snapshot += 1
        if self._since_snapshot >= SNAPSHOT_OVERDUE * self._settings.snapshot_every:
            self.snapshot()  # never idle (a continuous stream): bound the replay anyway

    def snapshot(self) -> None:
        self.store.save_snapshot(
            self._last_log_id, capture(self.slam), keep=self._settings.snapshots_kept
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
    def submit(self, body: dict[str, Any]) -> dict[str, Any]:
        """Take one frame object.

        Returns {"result_json" (the frame result as JSON text, exactly as stored),
        "replayed" (True for an idempotent retry answered from the log), "timing_ms",
        "store_ms", "event_ids", "live", "marginalised"}.
        """
        t0 = time.perf_counter()
        frame, text = canonical_frame(body)
        stored = self.store.find_frame(frame.robot, frame.seq)
        if stored is not None:
            if stored.body == text and stored.result is not None:
                return {"result_json": stored.result, "replayed": True, "event_ids": []}
            raise ServiceError(
                409,
                "duplicate-seq",
                "Duplicate frame",
                f"seq: robot {frame.robot!r} already sent a different frame with seq "
                f"{frame.seq}; a retry must repeat the frame exactly",
                field="seq",
            )
        last = last_accepted(self.slam).get(frame.robot)
        try:
            validate_frame(
                frame,
                last_seq=None if last is None else last[0],
                last_stamp=None if last is None else last[1],
            )
        except OutOfOrderFrame as exc:
            raise out_of_order(exc.field, exc.detail) from exc
        except InvalidFrame as exc:
            raise invalid_frame(exc.field, exc.detail) from exc
        log_id = self.store.append_frame(frame.robot, frame.seq, text)
        t1 = time.perf_counter()
        try:
            outcome = self.slam.process(frame, with_covariance=True)
        except InvalidFrame as exc:
            self.store.delete_frame(log_id)
            self._removals.take()
            raise invalid_frame(exc.field, exc.detail) from exc
        except EstimationError as exc:
            self.store.delete_frame(log_id)
            self._removals.take()
            self.slam, self._last_log_id, self._since_snapshot = self._load()
            raise ServiceError(
                422,
                "estimation-failed",
                "Estimation failed",
                f"the estimator could not take this frame ({exc}); the map is as before",
            ) from exc
        removals = self._removals.take()
        result = self._result_doc(self.slam, outcome, log_id, {"log": 1e3 * (t1 - t0)})
        t2 = time.perf_counter()
        text = json.dumps(result)
        event_ids = self._complete(self.slam, log_id, text, outcome, removals)
        store_ms = 1e3 * (time.perf_counter() - t2)
        self._last_log_id = log_id
        self._timing.append(1e3 * (time.perf_counter() - t0))
        self._count_frame()
        return {
            "result_json": text,
            "timing_ms": result["timing_ms"],
            "replayed": False,
            "event_ids": event_ids,
            "live": outcome.live,
            "marginalised": len(outcome.marginalised),
            "store_ms": store_ms,
        }

    def _result_doc(
        self, slam: BearingSlam, outcome: FrameOutcome, log_id: int, timing: dict[str, float]
    ) -> dict[str, Any]:
        cov = outcome.covariance
        return {
            "frame_id": log_id,
            "robot": outcome.robot,
            "seq": outcome.seq,
            "stamp": outcome.stamp,
            "pose": {"x": outcome.pose.x, "y": outcome.pose.y, "theta": outcome.pose.theta},
            "covariance": None if cov is None else np.asarray(cov).tolist(),
            "localisation": {"status": "tracking", "place": None, "confidence": None},
            "landmarks": {
                "observed": list(outcome.observed),
                "added": list(outcome.added),
                "marginalised": list(outcome.marginalised),
                "live": outcome.live,
            },
            "timing_ms": {**outcome.timing_ms, **timing},
        }

    def _complete(
        self,
        slam: BearingSlam,
        log_id: int,
        result_json: str,
        outcome: FrameOutcome,
        removals: list[RemovalRecord],
    ) -> list[int]:
        events: list[tuple[str, str]] = [("frame", result_json)]
        for lid in outcome.added:
            if lid in slam.landmarks:
                x, y = (float(v) for v in slam.landmark_position(lid))
                doc = {"id": lid, "label": slam.landmarks[lid].label, "x": x, "y": y}
                events.append(("landmark_added", json.dumps({**doc, "frame_id": log_id})))
        rows = []
        for r in removals:
            doc = {**r.as_dict(), "frame_id": log_id}
            events.append(("landmark_marginalised", json.dumps(doc)))
            rows.append((r.landmark_id, r.frame, json.dumps(doc)))
        return self.store.complete_frame(log_id, result_json, events, rows)

    # ------------------------------------------------------------ queries
    def summary(self) -> dict[str, Any]:
        ms = np.asarray(self._timing) if self._timing else None
        return {
            **self.record.as_dict(),
            "estimator": slam_config_dict(self.slam.config),
            "counts": {
                "frames": self.slam.frame_count,
                "robots": len(self.slam.robots),
                "live_landmarks": len(self.slam.landmarks),
                "candidates": self.slam.candidate_count,
                "removals": self.store.removal_count(),
                "graph_variables": self.slam.graph.num_variables,
                "graph_factors": self.slam.graph.num_factors,
                "replay_errors": self.replay_errors,
            },
            "robots": self.slam.robots,
            "timing_ms": None
            if ms is None
            else {
                "frames": len(ms),
                "mean": float(ms.mean()),
                "p50": float(np.percentile(ms, 50)),
                "p99": float(np.percentile(ms, 99)),
            },
        }

    def _seed(self) -> int:
        return MapConfig.model_validate(self.record.config).seed

    def pose(self) -> dict[str, Any]:
        return pose_doc(self.slam, self.record.id)

    def trajectory(
        self, robot: str | None = None, *, stats_every: int = 0
    ) -> dict[str, list[dict[str, Any]]]:
        rows: dict[str, list[dict[str, Any]]] = dict(
            trajectory_doc(self.slam, self.record.id, robot)
        )
        if stats_every > 0:
            labels = self.store.removed_labels()
            labels.update((lid, rec.label) for lid, rec in self.slam.landmarks.items())
            attach_frame_stats(rows, self.store.frame_stats(), labels, every=stats_every)
        return rows

    def landmarks(self) -> list[dict[str, Any]]:
        return landmarks_doc(self.slam, self._seed())

    def coverage(self, *, cell_m: float, radius_m: float, removals: int) -> dict[str, Any]:
        return coverage_doc(
            self.slam,
            self.store,
            self.record.id,
            self._seed(),
            cell_m=cell_m,
            radius_m=radius_m,
            removals=removals,
        )

    # ------------------------------------------------------------ export / import
    def export(self) -> dict[str, Any]:
        frames = []
        for stored in self.store.frames_after(0):
            frames.append(
                {
                    "frame": json.loads(stored.body),
                    "result": None if stored.result is None else json.loads(stored.result),
                }
            )
        return {
            "format": EXPORT_FORMAT,
            "version": EXPORT_VERSION,
            "exported": time.time(),
            "map": self.record.as_dict(),
            "estimator": slam_config_dict(self.slam.config),
            "landmarks": self.landmarks(),
            "trajectories": self.trajectory(),
            "removals": self.store.removals(),
            "frames": frames,
        }

    def import_frames(self, frames: list[dict[str, Any]]) -> None:
        """Replay an export's frame log into this (new, empty) map."""
        for i, item in enumerate(frames):
            if not isinstance(item, dict) or not isinstance(item.get("frame"), dict):
                raise ServiceError(
                    422,
                    "invalid-import",
                    "Invalid map document",
                    f"frames[{i}].frame: must be a frame object",
                    field=f"frames[{i}].frame",
                )
            try:
                self.submit(item["frame"])
            except ServiceError as exc:
                raise ServiceError(
                    422,
                    "invalid-import",
                    "Invalid map document",
                    f"frames[{i}].frame: {exc.detail}",
                    field=f"frames[{i}].frame",
                ) from exc
        self.snapshot()
