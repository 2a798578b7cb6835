"""Feed frames through one map's pipeline in-process and record what it cost.

This is the offline twin of ``POST /v1/maps/{id}/frames``: the same frames through
the same `MapPipeline` (service.pipeline), no HTTP, no store -- and no place
localiser: every frame goes to the estimator, as from a robot that always tracks.
"""

from __future__ import annotations

import json
import logging
import os
import resource
import tempfile
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from frontend.pipeline import FrontEnd
from graph.config import SlamConfig
from graph.slam import BearingSlam, RemovalRecord
from graph.trajectory import PoseRow, with_final_rows
from graph.types import FrameInput
from service.offline.evaluation import Trajectory
from service.offline.frame_files import FrameFileError, read_frame_lines
from service.pipeline import ImageFeatures, MapPipeline
from service.pipeline.images import ImageFrontEnd

log = logging.getLogger(__name__)

_PAGE_MB = os.sysconf("SC_PAGE_SIZE") / 2**20


def current_rss_mb() -> float:
    """Resident set size of this process now, MiB (Linux /proc)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return peak_rss_mb()
    return pages * _PAGE_MB


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far (since the last `reset_peak_rss()`,
    if any), MiB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def reset_peak_rss() -> bool:
    """Restart the peak-RSS count from the current RSS (Linux >= 4.0: ``echo 5 >
    /proc/self/clear_refs`` resets the high-water mark that ru_maxrss and VmHWM report).
    False where the kernel does not offer it."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


class RemovalLog:
    """An append-only removal log spooled to disk, so a long replay's memory stays flat."""

    def __init__(self) -> None:
        self._file = tempfile.TemporaryFile("w+", encoding="utf-8")  # noqa: SIM115
        self.count = 0
        self.first_frame: int | None = None

    def append(self, record: RemovalRecord) -> None:
        self._file.write(json.dumps(record.as_dict()) + "\n")
        self.count += 1
        if self.first_frame is None:
            self.first_frame = record.frame

    def read(self) -> list[dict[str, Any]]:
        self._file.flush()
        self._file.seek(0)
        rows = [json.loads(line) for line in self._file]
        self._file.seek(0, os.SEEK_END)
        return rows


_POSE_RECORD = np.dtype([("robot", "<i4"), ("seq", "<i8"), ("stamp", "<f8"), ("pose", "<f8", (3,))])


class PoseLog:
    """Final trajectory rows spooled to disk (the estimator's trajectory sink, see
    graph.trajectory), so a long replay's memory stays flat."""

    def __init__(self) -> None:
        self._file = tempfile.TemporaryFile("w+b")  # noqa: SIM115
        self._robots: dict[str, int] = {}

    def __call__(self, rows: list[PoseRow]) -> None:
        records = np.empty(len(rows), dtype=_POSE_RECORD)
        for i, r in enumerate(rows):
            slot = self._robots.setdefault(r.robot, len(self._robots))
            records[i] = (slot, r.seq, r.stamp, (r.x, r.y, r.theta))
        self._file.write(records.tobytes())

    def rows(self, robot: str) -> NDArray[np.float64]:
        """One robot's spooled rows, (N, 5) seq, stamp, x, y, theta in spooling order."""
        if robot not in self._robots:
            return np.zeros((0, 5))
        self._file.flush()
        self._file.seek(0)
        records = np.frombuffer(self._file.read(), dtype=_POSE_RECORD)
        self._file.seek(0, os.SEEK_END)
        mine = records[records["robot"] == self._robots[robot]]
        return np.column_stack([mine["seq"].astype(np.float64), mine["stamp"], mine["pose"]])


@dataclass
class ReplayResult:
    """What a replay produced: the map and the per-frame figures."""

    slam: BearingSlam
    frame_ms: list[float] = field(default_factory=list)
    """Processing time of each frame in order (until its result), milliseconds."""
    upkeep_ms: list[float] = field(default_factory=list)
    """The upkeep after each frame (SlamConfig.upkeep "after_frame"; ~0 otherwise), ms."""
    live_landmarks: list[int] = field(default_factory=list)
    """Live landmark count after each frame."""
    rss_mb: list[tuple[int, float]] = field(default_factory=list)
    """(frames processed, current RSS MiB), sampled."""
    removal_log: RemovalLog = field(default_factory=lambda: RemovalLog())
    """Every removal, spooled to a temporary file (not kept in memory)."""
    image_frames: int = 0
    """Frames whose observations came from the front end."""
    image_observations: int = 0
    """Bearing factors to live landmarks those frames added."""
    pose_log: PoseLog | None = None
    """The final trajectory rows, when the estimator spools them (its trajectory sink)."""

    def trajectory(self, robot: str) -> Trajectory:
        """The latest estimate of every frame's pose of one robot."""
        rows = self.slam.trajectory(robot)[robot]
        if self.pose_log is not None:
            rows = with_final_rows(self.pose_log.rows(robot), rows)
        return Trajectory.from_poses(rows[:, 1], rows[:, 2:5])

    def stats(self) -> dict[str, Any]:
        """The --stats document (JSON-serialisable)."""
        ms = np.asarray(self.frame_ms)
        return {
            "config": _config_dict(self.slam.config),
            "frames": len(self.frame_ms),
            "graph_frames": self.slam.graph_frame_count,
            "frame_ms": [round(t, 4) for t in self.frame_ms],
            "live_landmarks": self.live_landmarks,
            "removals": self.removal_log.read(),
            "peak_rss_mb": peak_rss_mb(),
            "rss_mb": self.rss_mb,
            "median_frame_ms": float(np.median(ms)) if ms.size else None,
            "image_frames": self.image_frames,
            "image_landmark_observations": self.image_observations,
            "p99_frame_ms": float(np.percentile(ms, 99)) if ms.size else None,
        }


@dataclass(frozen=True)
class ImageFrame:
    """A frame whose observations come from an image file (the front end runs on it)."""

    frame: FrameInput
    image_path: Path


def read_replay_frames(path: str | os.PathLike[str]) -> list[FrameInput | ImageFrame]:
    """The frames of a JSON-lines file; a frame with ``"image": "rel/path.png"`` (relative
    to the file's folder) becomes an ImageFrame, its ``observations`` ignored.

    Raises:
        FrameFileError: naming the 1-based line and the offending field.
    """
    p = Path(path)
    out: list[FrameInput | ImageFrame] = []
    for lineno, doc, frame in read_frame_lines(p):
        image = doc.get("image")
        if image is None:
            out.append(frame)
        elif not isinstance(image, str) or not image:
            raise FrameFileError(str(p), lineno, "image", "must be a relative path string")
        else:
            out.append(ImageFrame(frame, p.parent / image))
    return out


def _config_dict(config: SlamConfig) -> dict[str, Any]:
    return {name: getattr(config, name) for name in config.__slots__}


def spooled_map(config: SlamConfig, seed: int, *, release_heap: bool = True) -> ReplayResult:
    """A fresh map whose removal log and final trajectory rows are spooled to temporary
    files (so a long replay's memory stays flat), in an empty ReplayResult."""
    removal_log, pose_log = RemovalLog(), PoseLog()
    slam = BearingSlam(
        config,
        rng=np.random.default_rng(seed),
        removal_sink=removal_log.append,
        release_heap=release_heap,
        trajectory_sink=pose_log,
    )
    return ReplayResult(slam, removal_log=removal_log, pose_log=pose_log)


def replay(
    frames: Iterable[FrameInput | ImageFrame],
    *,
    config: SlamConfig,
    seed: int = 0,
    total: int | None = None,
    progress: bool | None = None,
    rss_every: int = 100,
    with_covariance: bool = False,
    front_end: FrontEnd | None = None,
) -> ReplayResult:
    """Process `frames` in order through a fresh map.

    `progress`: None shows a bar only when stderr is a terminal. An ImageFrame
    goes through `front_end` (required then) before the estimator.
    """
    result = spooled_map(config, seed)
    slam = result.slam
    images = None if front_end is None else ImageFrontEnd(slam, front_end)
    pipeline = MapPipeline(slam, localiser=None, images=images, pose_covariance=with_covariance)
    bar = tqdm(
        frames, total=total, unit="frame", disable=None if progress is None else not progress
    )
    for item in bar:
        t0 = time.perf_counter()
        if isinstance(item, ImageFrame):
            if front_end is None:
                raise ValueError("an image frame needs a front end (a camera config)")
            features = front_end.features(item.image_path.read_bytes())
            out = pipeline.step(item.frame, image=ImageFeatures(features)).outcome
            assert out is not None
            result.image_frames += 1
            result.image_observations += len(out.observed)
        else:
            out = pipeline.step(item).outcome
        assert out is not None
        t1 = time.perf_counter()
        pipeline.upkeep()
        result.frame_ms.append(1e3 * (t1 - t0))
        result.upkeep_ms.append(1e3 * (time.perf_counter() - t1))
        result.live_landmarks.append(len(slam.landmarks))
        if slam.frame_count % rss_every == 0:
            result.rss_mb.append((slam.frame_count, current_rss_mb()))
            bar.set_postfix(live=out.live, ms=f"{np.median(result.frame_ms[-rss_every:]):.1f}")
    slam.settle()
    log.info("replayed %d frames, %d removals", slam.frame_count, slam.removal_count)
    return result
