"""`covslam replay` and `covslam simulate` end to end, in-process."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from api.cli import main
from service.offline.datasets.mrclam import default_mrclam_dir
from service.offline.evaluation import read_tum


def test_simulate_then_replay_writes_trajectory_and_stats(tmp_path: Path, capsys) -> None:
    frames, gt = tmp_path / "run.jsonl", tmp_path / "gt.tum"
    assert (
        main(
            [
                "simulate",
                str(frames),
                "--ground-truth",
                str(gt),
                "--frames",
                "400",
                "--landmarks",
                "60",
                "--seed",
                "4",
            ]
        )
        == 0
    )
    traj, stats = tmp_path / "est.tum", tmp_path / "stats.json"
    assert (
        main(
            [
                "replay",
                str(frames),
                "--landmark-cap",
                "10",
                "--policy",
                "coverage",
                "--seed",
                "1",
                "--trajectory",
                str(traj),
                "--stats",
                str(stats),
                "--ground-truth",
                str(gt),
                "--no-progress",
            ]
        )
        == 0
    )
    doc = json.loads(stats.read_text())
    assert len(doc["frame_ms"]) == 400 == len(doc["live_landmarks"])
    assert max(doc["live_landmarks"]) <= 10
    assert doc["removals"], "a cap of 10 among 60 landmarks must remove some"
    assert {"landmark_id", "reason", "policy", "details"} <= set(doc["removals"][0])
    assert doc["peak_rss_mb"] > 0
    est = read_tum(traj)
    assert len(est) == 400
    assert 0.0 < doc["ate_rmse_m"] < 0.5  # metres, over about 40 m of travel
    assert "ATE RMSE" in capsys.readouterr().out


def test_replay_refuses_unknown_policy(tmp_path: Path) -> None:
    with pytest.raises(SystemExit):
        main(["replay", str(tmp_path / "x.jsonl"), "--policy", "nonsense"])


@pytest.mark.skipif(
    not default_mrclam_dir().is_dir(),
    reason=f"MRCLAM dataset 6 not found at {default_mrclam_dir()} (set COVSLAM_DATA)",
)
def test_mrclam_smoke_replay(tmp_path: Path) -> None:
    """Robot 1 of MRCLAM-6 with a cap of 8: beats dead reckoning by a wide margin."""
    stats = tmp_path / "stats.json"
    assert (
        main(
            [
                "replay",
                "mrclam",
                str(default_mrclam_dir()),
                "--robot",
                "1",
                "--landmark-cap",
                "8",
                "--stats",
                str(stats),
                "--no-progress",
            ]
        )
        == 0
    )
    doc = json.loads(stats.read_text())
    assert max(doc["live_landmarks"]) <= 8
    assert doc["ate_rmse_m"] < 0.5 * doc["dead_reckoning_ate_rmse_m"]
