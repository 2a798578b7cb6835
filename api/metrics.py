"""Prometheus metrics of the API process (one registry per app)."""

from __future__ import annotations

import contextlib
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

from service.frame_results import FrameReply

_BUCKETS_MS = (0.5, 1, 2, 3, 5, 7.5, 10, 15, 25, 50, 100, 250, 500, 1000, 2500, 10000)


class Metrics:
    """Frames, per-stage latency, live landmarks, marginalisations, worker restarts."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.frames = Counter(
            "covslam_frames",
            "Frames processed (retries answered from the log excluded)",
            ["map"],
            registry=self.registry,
        )
        self.replayed = Counter(
            "covslam_frames_replayed",
            "Idempotent retries answered from the log",
            ["map"],
            registry=self.registry,
        )
        self.stage = Histogram(
            "covslam_frame_stage_milliseconds",
            "Time per frame and stage, milliseconds (worker stages; 'http' = whole request)",
            ["stage"],
            buckets=_BUCKETS_MS,
            registry=self.registry,
        )
        self.live = Gauge(
            "covslam_live_landmarks", "Live landmarks per map", ["map"], registry=self.registry
        )
        self.marginalisations = Counter(
            "covslam_marginalisations",
            "Landmarks marginalised by the budget",
            ["map"],
            registry=self.registry,
        )
        self.restarts = Counter(
            "covslam_worker_restarts",
            "Worker processes restarted after a crash",
            registry=self.registry,
        )
        self.rejected = Counter(
            "covslam_frames_rejected",
            "Frames refused with a 4xx/5xx",
            ["status"],
            registry=self.registry,
        )
        # Every frame updates a dozen series: their children are looked up once (a
        # `labels` call checks and locks each time).
        self._stages: dict[str, Any] = {}
        self._maps: dict[str, tuple[Any, Any, Any]] = {}

    def _stage(self, stage: str) -> Any:
        child = self._stages.get(stage)
        if child is None:
            child = self._stages[stage] = self.stage.labels(stage)
        return child

    def record_frame(self, map_id: str, reply: FrameReply, http_ms: float) -> None:
        if reply.replayed:
            self.replayed.labels(map_id).inc()
            return
        series = self._maps.get(map_id)
        if series is None:
            series = self._maps[map_id] = (
                self.frames.labels(map_id),
                self.live.labels(map_id),
                self.marginalisations.labels(map_id),
            )
        frames, live, marginalisations = series
        frames.inc()
        for stage, ms in reply.timing_ms.items():
            self._stage(stage).observe(ms)
        self._stage("store").observe(reply.store_ms)
        self._stage("http").observe(http_ms)
        live.set(reply.live)
        marginalisations.inc(reply.marginalised)

    def forget(self, map_id: str) -> None:
        """Drop a deleted map's series."""
        self._maps.pop(map_id, None)
        for metric in (self.frames, self.replayed, self.live, self.marginalisations):
            with contextlib.suppress(KeyError):  # no series yet for this map
                metric.remove(map_id)
