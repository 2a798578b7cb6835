"""Write a rendered run as files that `covslam replay` (and an HTTP client) can post.

Layout of the output folder:

    frames.jsonl   one frame per line (the REST frame format) without observations,
                   plus ``"image": "images/000017.png"``: the frame's image, a path
                   relative to the frames file
    images/        the PNGs (8-bit grayscale)
    camera.json    the camera config (frontend.cameras.camera_from_config)
    ground_truth.tum

Everything random comes from the `rng` passed in: a seed gives the same files.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from frontend.cameras import CameraModel, OmniCamera, PanoramaCamera
from service.frames_io import frame_to_dict
from service.offline.datasets.indoor_sim import make_world, simulate
from service.offline.datasets.render import make_textured_world, render_omni, render_panorama
from service.offline.evaluation import write_tum

__all__ = ["RenderedRun", "write_rendered_run"]


@dataclass(frozen=True)
class RenderedRun:
    """Where a written run's files are."""

    frames_path: Path
    camera_path: Path
    ground_truth_path: Path
    frames: int


def write_rendered_run(
    out_dir: str | os.PathLike[str],
    *,
    frames: int,
    rng: np.random.Generator,
    camera: CameraModel | None = None,
    rooms: tuple[int, int] = (3, 3),
    door_probability: float = 0.5,
) -> RenderedRun:
    """Render `frames` frames of a robot driving the indoor world; write them to `out_dir`."""
    camera = camera or PanoramaCamera()
    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    world = make_world(rooms=rooms, landmarks=rooms[0] * rooms[1], rng=rng)
    textured = make_textured_world(world, rng=rng)
    run = simulate(world, frames=frames, rng=rng, door_probability=door_probability)
    truth = run.ground_truth.poses()
    frames_path = out / "frames.jsonl"
    with frames_path.open("w", encoding="utf-8") as fh:
        for k, frame in enumerate(run.frames):
            if isinstance(camera, OmniCamera):
                image = render_omni(textured, truth[k], camera)
            else:
                image, _ = render_panorama(textured, truth[k], camera)
            name = f"images/{k:06d}.png"
            if not cv2.imwrite(str(out / name), image):
                raise OSError(f"could not write {out / name}")
            doc = frame_to_dict(frame)
            del doc["observations"]
            doc["image"] = name
            fh.write(json.dumps(doc, separators=(",", ":")) + "\n")
    camera_path = out / "camera.json"
    camera_path.write_text(json.dumps(camera.as_config(), indent=1))
    gt_path = out / "ground_truth.tum"
    write_tum(gt_path, run.ground_truth)
    return RenderedRun(frames_path, camera_path, gt_path, frames)
