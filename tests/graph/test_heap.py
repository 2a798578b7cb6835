"""graph.heap: freed heap pages go back to the OS, and releasing them changes nothing."""

from __future__ import annotations

import sys

import numpy as np
import pytest

import graph.slam
from graph.config import SlamConfig
from graph.heap import heap_release_available, release_free_heap
from graph.slam import BearingSlam
from service.offline.replay import current_rss_mb
from tests.graph._world import circle_frames

needs_trim = pytest.mark.skipif(
    not (sys.platform.startswith("linux") and heap_release_available()),
    reason="needs glibc's malloc_trim and /proc (Linux)",
)


@needs_trim
def test_free_pages_between_live_blocks_are_released() -> None:
    """Blocks below glibc's mmap threshold live in its heap: freeing all but every tenth
    leaves free regions between live ones, which stay resident until malloc_trim."""
    size, count = 64 * 1024, 1500  # ~94 MiB of heap blocks, each touched (zeroed)
    blocks = [bytearray(size) for _ in range(count)]
    keep = blocks[::10]
    del blocks
    before = current_rss_mb()
    freed = size * (count - len(keep)) / 2**20  # ~84 MiB
    assert release_free_heap()
    after = current_rss_mb()
    assert before - after > 0.5 * freed, (before, after, freed)
    assert all(len(b) == size for b in keep)  # what is live is untouched


def _trajectory(release: bool, monkeypatch: pytest.MonkeyPatch) -> tuple[np.ndarray, int, int]:
    calls = 0

    def counting() -> bool:
        nonlocal calls
        calls += 1
        return release_free_heap()

    monkeypatch.setattr(graph.slam, "release_free_heap", counting)
    frames, _, _ = circle_frames(200, seed=4, n_landmarks=30)
    # Tracked frames (graph_frame_distance_m) do not update the graph: no release.
    cfg = SlamConfig(landmark_cap=8, pose_window=15, max_keyframes=6, graph_frame_distance_m=0.3)
    slam = BearingSlam(cfg, rng=np.random.default_rng(4), release_heap=release)
    for f in frames:
        slam.process(f, with_covariance=False)
    slam.settle()  # the last graph frame's upkeep
    assert slam.removal_count > 0
    return slam.trajectory()["r1"], calls, slam.graph_frame_count


def test_release_after_graph_updates_leaves_the_estimate_bit_identical(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    released, calls, graph_frames = _trajectory(True, monkeypatch)
    kept, no_calls, _ = _trajectory(False, monkeypatch)
    assert calls == graph_frames < len(released)
    assert no_calls == 0
    np.testing.assert_array_equal(released, kept)
