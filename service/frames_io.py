"""Frame documents as Python objects and JSON lines.

`frame_from_dict` parses a frame document through the frame model
(`service.frame_model`: strict structure and types, the offending field named with a
dotted path such as ``observations[2].bearing``); `frame_to_dict` is its inverse.

Units: metres, radians, seconds (stamps are seconds, any epoch).

A frame file is JSON lines: one frame object per line, blank lines skipped.
Paths ending in ``.gz`` are read and written gzip-compressed.
"""

from __future__ import annotations

import gzip
import json
import os
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import IO, Any

from graph.errors import InvalidFrame
from graph.types import FrameInput
from service.errors import invalid_frame
from service.frame_model import FrameLimits, parse_frame

__all__ = [
    "FrameFileError",
    "admit_frame",
    "frame_from_dict",
    "frame_to_dict",
    "read_frames",
    "write_frames",
]


class FrameFileError(ValueError):
    """A line of a frame file could not be read as a frame.

    `path` and `line` (1-based) locate it; `field` is the offending field's
    dotted path (``"line"`` when the line is not JSON at all); `detail` says
    what was wrong.
    """

    def __init__(self, path: str, line: int, field: str, detail: str) -> None:
        super().__init__(f"{path}:{line}: {field}: {detail}")
        self.path = path
        self.line = line
        self.field = field
        self.detail = detail


# --------------------------------------------------------------------------- parsing

IMAGE_MEMBER = "image"
"""A frame document's reference to its image: a relative path in a frame file, the
image's digest in a map's log and in exports. It is not part of the frame itself (the
image comes beside it), so `frame_from_dict` sets it aside; a posted JSON frame must
not have it."""


def frame_from_dict(d: Mapping[str, Any], *, limits: FrameLimits | None = None) -> FrameInput:
    """Parse one frame document (a frame object, perhaps with an ``image`` member).

    The frame is validated by `service.frame_model.FrameIn` (see `parse_frame`): with
    `limits`, its bounds too. Units: metres, radians, seconds.

    Raises:
        InvalidFrame: with the dotted path of the first offending field.
    """
    if isinstance(d, Mapping) and IMAGE_MEMBER in d:
        d = {k: v for k, v in d.items() if k != IMAGE_MEMBER}
    return parse_frame(d, limits=limits)


def admit_frame(doc: object, limits: FrameLimits, *, image_frame: bool = False) -> None:
    """Check a posted frame against the frame model and `limits` before it goes to its
    map: a JSON frame as it is, an image frame's `meta` as a frame document.

    Raises:
        ServiceError: 422 naming the field.
    """
    try:
        if image_frame and isinstance(doc, Mapping):
            frame_from_dict(doc, limits=limits)
        else:
            parse_frame(doc, limits=limits)
    except InvalidFrame as exc:
        raise invalid_frame(exc.field, exc.detail) from exc


# --------------------------------------------------------------------------- writing


def frame_to_dict(frame: FrameInput) -> dict[str, Any]:
    """The JSON object of a frame; the inverse of `frame_from_dict`.

    Fields that are None are omitted; ``observations`` is always present.
    """
    out: dict[str, Any] = {"robot": frame.robot, "seq": frame.seq, "stamp": frame.stamp}
    if frame.odometry is not None:
        odo = frame.odometry
        odo_d: dict[str, float] = {"dx": odo.dx, "dy": odo.dy, "dtheta": odo.dtheta}
        for key, value in (
            ("sigma_x", odo.sigma_x),
            ("sigma_y", odo.sigma_y),
            ("sigma_theta", odo.sigma_theta),
        ):
            if value is not None:
                odo_d[key] = value
        out["odometry"] = odo_d
    if frame.initial_pose is not None:
        p = frame.initial_pose
        out["initial_pose"] = {"x": p.x, "y": p.y, "theta": p.theta}
    observations = []
    for ob in frame.observations:
        ob_d: dict[str, Any] = {"bearing": ob.bearing_rad}
        if ob.sigma_rad is not None:
            ob_d["sigma"] = ob.sigma_rad
        ob_d["label"] = ob.label
        observations.append(ob_d)
    out["observations"] = observations
    return out


# --------------------------------------------------------------------------- files


def _open_text(path: Path, *, write: bool) -> IO[str]:
    """Open a text file, gzip-compressed when the name ends in ``.gz``."""
    if path.suffix == ".gz":
        return gzip.open(path, "wt" if write else "rt", encoding="utf-8")
    return path.open("w" if write else "r", encoding="utf-8")


def read_frame_lines(
    path: str | os.PathLike[str],
) -> Iterator[tuple[int, dict[str, Any], FrameInput]]:
    """Yield (1-based line number, JSON object, frame) for each frame of a JSON-lines file.

    Blank lines are skipped; the file (plain or ``.gz``) is read lazily, line by line.

    Raises:
        FrameFileError: naming the line number and the offending field.
    """
    p = Path(path)
    with _open_text(p, write=False) as fh:
        for lineno, line in enumerate(fh, start=1):
            if not line.strip():
                continue
            try:
                d = json.loads(line)
            except json.JSONDecodeError as exc:
                raise FrameFileError(str(p), lineno, "line", f"not JSON: {exc.msg}") from exc
            try:
                frame = frame_from_dict(d)
            except InvalidFrame as exc:
                raise FrameFileError(str(p), lineno, exc.field, exc.detail) from exc
            yield lineno, d, frame


def read_frames(path: str | os.PathLike[str]) -> Iterator[FrameInput]:
    """Yield the frames of a JSON-lines file in file order (see read_frame_lines)."""
    for _, _, frame in read_frame_lines(path):
        yield frame


def write_frames(path: str | os.PathLike[str], frames: Iterable[FrameInput]) -> int:
    """Write frames as JSON lines (standard JSON: NaN/inf refused); return the count.

    Floats are written with Python's shortest round-trip repr, so reading the
    file back gives equal frames.
    """
    p = Path(path)
    count = 0
    with _open_text(p, write=True) as fh:
        for frame in frames:
            fh.write(json.dumps(frame_to_dict(frame), allow_nan=False, separators=(",", ":")))
            fh.write("\n")
            count += 1
    return count
