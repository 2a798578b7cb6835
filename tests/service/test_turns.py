"""On-the-spot 90-degree turns through a camera map: the robot keeps track."""

from __future__ import annotations

import math

import numpy as np
import pytest

from graph.localiser import LOST
from service.offline.datasets.camera_runs import render_turn_run, run_turns, turn_path


def test_turn_path_turns_on_the_spot_by_quarter_turns() -> None:
    poses, turning = turn_path(legs=2, leg_m=0.5, step_m=0.1, turn_frames=3, spin_turns=4)
    steps = np.diff(poses, axis=0)
    turned = np.abs(np.angle(np.exp(1j * steps[:, 2])))
    # A turn frame moves nowhere and turns a third of 90 degrees; a drive frame the reverse.
    assert np.allclose(np.hypot(steps[turning[1:], 0], steps[turning[1:], 1]), 0.0)
    assert np.allclose(turned[turning[1:]], math.pi / 6)
    assert np.allclose(turned[~turning[1:]], 0.0)
    # 2 legs, a turn after each, then 3 more quarter turns of the spin: 5 turns of 3 frames.
    assert int(turning.sum()) == 15
    assert not turning[0]


@pytest.fixture(scope="module")
def turns() -> dict:
    """Two 1 m legs and a full spin, each 90-degree turn between two frames."""
    run = render_turn_run(rng=np.random.default_rng(3), turn_frames=1, legs=2, spin_turns=4)
    return run_turns(run, seed=3)


def test_quarter_turns_in_one_frame_never_lose_track(turns: dict) -> None:
    rows = turns["rows"]
    assert turns["turn_frames"] == 5
    assert LOST not in {r["status"] for r in rows}
    # The watch filter runs on the association's observations and can go lost.
    assert LOST not in {r["watch_status"] for r in rows}
    for k, r in enumerate(rows):
        if r["turning"]:
            assert r["error_m"] < 0.1, (k, r)
            assert r["error_deg"] < 3.0, (k, r)
            assert r["watch_error_m"] < 0.2, (k, r)
    # The landmarks seen before a turn are found again after it (no new map of the room).
    later = [k for k, r in enumerate(rows) if r["turning"] and k > 12]
    assert later
    for k in later:
        assert rows[k]["observed"] >= 0.5 * rows[k - 1]["observed"] > 0, (k, rows[k - 1 : k + 1])
        assert rows[k]["added"] <= 0.2 * rows[k]["observed"], (k, rows[k])


@pytest.fixture(scope="module")
def slipping() -> dict[bool, dict]:
    """The same path with odometry turns off by ~14 degrees (sigma), compass on and off."""
    return {
        compass: run_turns(
            render_turn_run(
                rng=np.random.default_rng(3),
                turn_frames=1,
                legs=2,
                spin_turns=4,
                odometry_noise=(0.02, 0.02, 0.15),
            ),
            seed=3,
            compass=compass,
        )
        for compass in (True, False)
    }


def test_the_compass_keeps_track_where_the_odometry_turn_is_wrong(slipping: dict) -> None:
    def worst_turn(rows: list[dict]) -> tuple[float, float]:
        """(smallest share of landmarks found again, largest heading error deg) over the
        turns once the map holds landmarks."""
        later = [k for k, r in enumerate(rows) if r["turning"] and k > 12]
        assert later
        found = min(rows[k]["observed"] / max(rows[k - 1]["observed"], 1) for k in later)
        return found, max(rows[k]["error_deg"] for k in later)

    found, error_deg = worst_turn(slipping[True]["rows"])
    assert found >= 0.5 and error_deg < 3.0, (found, error_deg)
    assert LOST not in {r["watch_status"] for r in slipping[True]["rows"]}
    # Without it, the prediction is as wrong as the odometry: the turn finds next to nothing.
    found, error_deg = worst_turn(slipping[False]["rows"])
    assert found < 0.2 and error_deg > 3.0, (found, error_deg)
