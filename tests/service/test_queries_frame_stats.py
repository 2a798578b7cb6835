"""Frame figures attached to trajectories (`service.queries.attach_frame_stats`)."""

from __future__ import annotations

from typing import Any

from service.queries import attach_frame_stats
from service.store import FrameFigures

COV = "[[0.01, 0.0, 0.0], [0.0, 0.04, 0.0], [0.0, 0.0, 0.001]]"


def _rows(robot: str, seqs: range) -> list[dict[str, Any]]:
    return [{"seq": s, "stamp": float(s), "x": 0.0, "y": 0.0, "theta": 0.0} for s in seqs]


def test_uncapped_counts_distinct_labels_and_every_nth_pose_is_picked() -> None:
    # Two robots interleaved in the log. Landmark 0 (label "a") is removed at frame 3 and
    # "a" comes back as landmark 2 at frame 5; landmark 3 is initialised and removed by
    # frame 6 itself (only in `marginalised`).
    stats = [
        FrameFigures(1, "r1", 0, 1, (0,), (), 5.0, COV),
        FrameFigures(2, "r2", 0, 2, (1,), (), 6.0, COV),
        FrameFigures(3, "r1", 1, 1, (), (0,), 7.0, None),
        FrameFigures(4, "r2", 1, 1, (), (), 8.0, COV),
        FrameFigures(5, "r1", 2, 2, (2,), (), 9.0, COV),
        FrameFigures(6, "r2", 2, 2, (), (3,), 10.0, COV),
    ]
    labels = {0: "a", 1: "b", 2: "a", 3: "c"}
    robots = {"r1": _rows("r1", range(3)), "r2": _rows("r2", range(3))}
    attach_frame_stats(robots, stats, labels, every=2)

    r1, r2 = robots["r1"], robots["r2"]
    assert [p.get("frame_id") for p in r1] == [1, None, 5]  # every 2nd, and the latest
    assert [p.get("frame_id") for p in r2] == [2, None, 6]
    assert [p.get("uncapped") for p in r1] == [1, None, 2]  # "a" back again counts once
    assert [p.get("uncapped") for p in r2] == [2, None, 3]  # "c" though removed at once
    assert r1[0]["covariance"] == [[0.01, 0.0, 0.0], [0.0, 0.04, 0.0], [0.0, 0.0, 0.001]]
    assert r1[2]["live"] == 2 and r1[2]["ms"] == 9.0
    assert "covariance" not in r1[1]


def test_no_figures_when_not_asked() -> None:
    robots = {"r1": _rows("r1", range(2))}
    attach_frame_stats(robots, [FrameFigures(1, "r1", 0, 0, (), (), 1.0, None)], {}, every=0)
    assert all(set(p) == {"seq", "stamp", "x", "y", "theta"} for p in robots["r1"])
