"""Frame files: JSON lines, one frame object per line, blank lines skipped; paths ending
in ``.gz`` are read and written gzip-compressed. Each line is a frame document
(service.frames_io)."""

from __future__ import annotations

import gzip
import json
import os
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, Any

from graph.errors import InvalidFrame
from graph.types import FrameInput
from service.frames_io import frame_from_dict, frame_to_dict

__all__ = ["FrameFileError", "read_frame_lines", "read_frames", "write_frames"]


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
