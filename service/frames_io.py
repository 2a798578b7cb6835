"""The REST frame format (DESIGN.md, "A frame (JSON form)") as Python objects and JSON lines.

`frame_from_dict` is strict about structure and types and names the offending
field with a dotted path (``observations[2].bearing``). It does not check that
numbers are finite or that bearings lie in (-pi, pi]: that is the graph
validator's job, so that every entry point refuses the same frames.

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
from graph.types import BearingObservation, FrameInput, Odometry, Pose2D

__all__ = [
    "FrameFileError",
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


def _json_type(value: object) -> str:
    """The JSON name of a Python value's type, for error details."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, int | float):
        return "number"
    if isinstance(value, str):
        return "string"
    if isinstance(value, list | tuple):
        return "array"
    if isinstance(value, Mapping):
        return "object"
    return type(value).__name__


def _object(value: object, field: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise InvalidFrame(field, f"must be an object, got {_json_type(value)}")
    return value


def _number(obj: Mapping[str, Any], key: str, path: str) -> float:
    """A required number (int or float, not bool) as float."""
    field = f"{path}.{key}" if path else key
    if key not in obj:
        raise InvalidFrame(field, "is required")
    value = obj[key]
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InvalidFrame(field, f"must be a number, got {_json_type(value)}")
    return float(value)


def _optional_number(obj: Mapping[str, Any], key: str, path: str) -> float | None:
    """An optional number; absent or null gives None."""
    if obj.get(key) is None:
        return None
    return _number(obj, key, path)


def _odometry(value: object) -> Odometry:
    obj = _object(value, "odometry")
    return Odometry(
        dx=_number(obj, "dx", "odometry"),
        dy=_number(obj, "dy", "odometry"),
        dtheta=_number(obj, "dtheta", "odometry"),
        sigma_x=_optional_number(obj, "sigma_x", "odometry"),
        sigma_y=_optional_number(obj, "sigma_y", "odometry"),
        sigma_theta=_optional_number(obj, "sigma_theta", "odometry"),
    )


def _pose(value: object) -> Pose2D:
    obj = _object(value, "initial_pose")
    return Pose2D(
        x=_number(obj, "x", "initial_pose"),
        y=_number(obj, "y", "initial_pose"),
        theta=_number(obj, "theta", "initial_pose"),
    )


def _label(obj: Mapping[str, Any], path: str) -> str:
    """A label as str; JSON integers are accepted and converted (17 -> "17")."""
    field = f"{path}.label"
    if obj.get("label") is None:
        if "descriptor" in obj:
            detail = "is required (descriptor-only observations are not supported yet)"
        else:
            detail = "is required"
        raise InvalidFrame(field, detail)
    value = obj["label"]
    if isinstance(value, bool) or not isinstance(value, int | str):
        raise InvalidFrame(field, f"must be a string or an integer, got {_json_type(value)}")
    label = str(value)
    if not label:
        raise InvalidFrame(field, "must not be empty")
    return label


def _observation(value: object, index: int) -> BearingObservation:
    path = f"observations[{index}]"
    obj = _object(value, path)
    bearing = _number(obj, "bearing", path)
    sigma = _optional_number(obj, "sigma", path)
    label = _label(obj, path)
    descriptor = obj.get("descriptor")
    if descriptor is not None and not isinstance(descriptor, str):
        raise InvalidFrame(
            f"{path}.descriptor", f"must be a base64 string, got {_json_type(descriptor)}"
        )
    return BearingObservation(bearing_rad=bearing, label=label, sigma_rad=sigma)


def frame_from_dict(d: Mapping[str, Any]) -> FrameInput:
    """Parse one frame from its JSON object (already decoded).

    Required: ``robot`` (non-empty string), ``seq`` (integer >= 0), ``stamp``
    (number, seconds). Optional: ``odometry`` {dx, dy [m], dtheta [rad],
    sigma_x, sigma_y [m], sigma_theta [rad]}, ``initial_pose`` {x, y [m],
    theta [rad]}, ``observations`` (array, absent means none) of {bearing [rad],
    sigma [rad] (optional), label (string or integer, stored as string),
    descriptor (optional base64 string, not kept)}. Optional fields may be null.
    Unknown keys are ignored. Booleans are not numbers.

    Raises:
        InvalidFrame: with the dotted path of the first offending field.
    """
    obj = _object(d, "frame")

    if "robot" not in obj:
        raise InvalidFrame("robot", "is required")
    robot = obj["robot"]
    if not isinstance(robot, str):
        raise InvalidFrame("robot", f"must be a string, got {_json_type(robot)}")
    if not robot:
        raise InvalidFrame("robot", "must not be empty")

    if "seq" not in obj:
        raise InvalidFrame("seq", "is required")
    seq = obj["seq"]
    if isinstance(seq, bool) or not isinstance(seq, int):
        kind = "non-integer number" if isinstance(seq, float) else _json_type(seq)
        raise InvalidFrame("seq", f"must be an integer, got {kind}")
    if seq < 0:
        raise InvalidFrame("seq", f"must be >= 0, got {seq}")

    stamp = _number(obj, "stamp", "")

    odometry = None if obj.get("odometry") is None else _odometry(obj["odometry"])
    initial_pose = None if obj.get("initial_pose") is None else _pose(obj["initial_pose"])

    raw_obs = obj.get("observations")
    if raw_obs is None:
        raw_obs = []
    if not isinstance(raw_obs, list | tuple):
        raise InvalidFrame("observations", f"must be an array, got {_json_type(raw_obs)}")
    observations = tuple(_observation(o, i) for i, o in enumerate(raw_obs))

    return FrameInput(
        robot=robot,
        seq=seq,
        stamp=stamp,
        odometry=odometry,
        initial_pose=initial_pose,
        observations=observations,
    )


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
