"""Frame documents as Python objects.

`frame_from_dict` parses a frame document through the frame model
(`service.frame_model`: strict structure and types, the offending field named with a
dotted path such as ``observations[2].bearing``); `frame_to_dict` is its inverse.
Frame files (JSON lines) are the offline tools' (service.offline.frame_files).

Units: metres, radians, seconds (stamps are seconds, any epoch).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from typing import Any

from graph.errors import InvalidFrame
from graph.types import FrameInput
from service.errors import invalid_frame
from service.frame_model import FrameLimits, parse_frame

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


def image_digest(image: bytes) -> dict[str, Any]:
    """What a frame's log entry records of its image (idempotency compares it)."""
    return {"sha256": hashlib.sha256(image).hexdigest(), "bytes": len(image)}


def canonical_frame(
    body: dict[str, Any],
    image: bytes | None = None,
    digest: dict[str, Any] | None = None,
    *,
    limits: FrameLimits | None = None,
) -> tuple[Any, str]:
    """Parse a frame object; (FrameInput, canonical JSON text used for idempotency).

    An image frame's text records the image's digest (``"image"``; given as `digest`
    for an imported frame, whose image is not at hand), so a retry must repeat the
    image too. The text of an image frame has no observations (they come from the
    image).

    `limits`: a posted frame, checked as `admit_frame` checks it (its bounds; a JSON
    frame must not name an image), so that one parse both checks and reads it.
    """
    try:
        if limits is not None and image is None and digest is None:
            frame = parse_frame(body, limits=limits)  # a posted JSON frame
        else:
            frame = frame_from_dict(body, limits=limits)
    except InvalidFrame as exc:
        raise invalid_frame(exc.field, exc.detail) from exc
    doc = frame_to_dict(frame)
    if image is not None or digest is not None:
        doc["image"] = image_digest(image) if image is not None else digest
        doc["observations"] = []
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"))
    return frame, text


def observations_json(observations: Any) -> str:
    """The JSON text of observations as the REST frame writes them."""
    doc = frame_to_dict(FrameInput(robot="-", seq=0, stamp=0.0, observations=tuple(observations)))
    return json.dumps(doc["observations"], separators=(",", ":"))


def image_record(value: Any, field: str) -> dict[str, Any]:
    """An export's record of an image (``{"sha256": hex, "bytes": n}``), checked."""
    ok = (
        isinstance(value, dict)
        and isinstance(value.get("sha256"), str)
        and len(value["sha256"]) == 64
        and all(ch in "0123456789abcdef" for ch in value["sha256"])
        and isinstance(value.get("bytes"), int)
        and not isinstance(value.get("bytes"), bool)
        and value["bytes"] > 0
    )
    if not ok:
        raise invalid_frame(field, 'must be {"sha256": 64 lowercase hex digits, "bytes": n > 0}')
    return {"sha256": value["sha256"], "bytes": value["bytes"]}
