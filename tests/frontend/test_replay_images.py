"""A short rendered sequence through the whole pipeline: files -> covslam replay -> map."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from api.cli import main
from frontend.cameras import PanoramaCamera
from service.offline.datasets.render_run import write_rendered_run
from service.offline.evaluation import read_tum
from service.offline.replay import ImageFrame, read_replay_frames


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("rendered")
    write_rendered_run(
        out, frames=60, rng=np.random.default_rng(7), camera=PanoramaCamera(1024, 256)
    )
    return out


def test_rendered_files_reference_their_images(rendered: Path) -> None:
    items = read_replay_frames(rendered / "frames.jsonl")
    assert len(items) == 60
    assert all(isinstance(it, ImageFrame) and it.image_path.is_file() for it in items)
    camera = json.loads((rendered / "camera.json").read_text())
    assert camera["model"] == "panorama" and camera["width"] == 1024


def test_replay_of_rendered_images_builds_a_map(rendered: Path, capsys) -> None:
    stats_path, traj_path = rendered / "stats.json", rendered / "est.tum"
    code = main(
        [
            "replay",
            str(rendered / "frames.jsonl"),
            "--landmark-cap",
            "none",
            "--ground-truth",
            str(rendered / "ground_truth.tum"),
            "--stats",
            str(stats_path),
            "--trajectory",
            str(traj_path),
            "--no-progress",
        ]
    )
    assert code == 0
    stats = json.loads(stats_path.read_text())
    assert stats["image_frames"] == 60
    # With a camera map's defaults, as the service creates one: graph frames and tracked ones.
    assert stats["config"]["graph_frame_distance_m"] > 0
    assert 0 < stats["graph_frames"] < 60
    # Tracks became landmarks, and later frames observed them by descriptor matching.
    assert stats["live_landmarks"][-1] > 10
    assert stats["image_landmark_observations"] > 100
    assert math.isfinite(stats["ate_rmse_m"])
    assert len(read_tum(traj_path)) == 60
    assert "ATE RMSE" in capsys.readouterr().out


def test_image_frame_with_a_bad_image_field_is_refused(tmp_path: Path) -> None:
    from service.offline.frame_files import FrameFileError

    path = tmp_path / "f.jsonl"
    path.write_text(
        '{"robot":"r1","seq":0,"stamp":0,"initial_pose":{"x":0,"y":0,"theta":0},"image":7}\n'
    )
    with pytest.raises(FrameFileError, match="image"):
        read_replay_frames(path)


def test_image_replay_takes_the_camera_loss_and_cap_unless_given() -> None:
    from api.cli import _config, build_parser, camera_map_config
    from graph.config import SlamConfig
    from service.pipeline.camera_config import CAMERA_LANDMARK_CAP, CAMERA_NOISE_DEFAULTS

    camera_cfg = PanoramaCamera(1024, 256).as_config()
    plain = build_parser().parse_args(["replay", "frames.jsonl"])
    assert _config(plain).huber_k == SlamConfig().huber_k
    assert _config(plain).bearing_loss == "huber"
    camera = camera_map_config(plain, camera_cfg)
    assert camera.bearing_loss == CAMERA_NOISE_DEFAULTS["bearing_loss"]
    assert camera.huber_k == CAMERA_NOISE_DEFAULTS["huber_k"]
    assert (_config(plain).landmark_cap, camera.landmark_cap) == (50, CAMERA_LANDMARK_CAP)
    capped = build_parser().parse_args(["replay", "frames.jsonl", "--landmark-cap", "none"])
    assert camera_map_config(capped, camera_cfg).landmark_cap is None

    given = build_parser().parse_args(["replay", "frames.jsonl", "--huber", "2.5"])
    kept = camera_map_config(given, camera_cfg)
    assert (kept.bearing_loss, kept.huber_k) == ("huber", 2.5)
    off = build_parser().parse_args(["replay", "frames.jsonl", "--huber", "none"])
    assert camera_map_config(off, camera_cfg).huber_k is None
