"""The associator's state as a JSON document (map export / import).

A snapshot pickles the `Associator`; an export document must not (unpickling an
uploaded document would run arbitrary code), so the state travels as plain JSON:
descriptors base64-encoded, poses as (x, y, theta) lists. `from_doc` checks every
field and raises `ValueError` naming it (``frontend.associator.tracks.r1[3].origin``).

Document (version 1)::

    {"version": 1, "descriptor": {"dtype": "uint8", "length": 32}, "next_track": 812,
     "landmarks": [{"label": "t000017", "descriptors": ["<b64>", ...],
                    "view_angles": [rad, ...], "height_m": 0.4 | null, "height_n": 3}],
     "archived": [same as landmarks: the views of landmarks no longer live; optional],
     "tracks": {"r1": [{"label", "descriptor", "origin": [x, y, theta], "bearing",
                        "elevation", "length", "missed",
                        "views": [{"descriptor", "pose": [x, y, theta], "bearing"}]}]}}
"""

from __future__ import annotations

import base64
import binascii
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from frontend.association import AssociationConfig, Associator, _Landmark, _Track

__all__ = ["STATE_VERSION", "associator_from_doc", "associator_to_doc"]

STATE_VERSION = 1
_DTYPES: dict[str, type[np.generic]] = {"uint8": np.uint8, "float32": np.float32}


def _encode(desc: NDArray[Any]) -> str:
    return base64.b64encode(np.ascontiguousarray(desc).tobytes()).decode("ascii")


def associator_to_doc(assoc: Associator) -> dict[str, Any]:
    """The associator's landmark views, tracks and label counter as JSON-ready data."""
    sample = next(
        (
            d
            for lm in (*assoc._landmarks.values(), *assoc._archived.values())
            for d in lm.descriptors
        ),
        next((t.descriptor for ts in assoc._tracks.values() for t in ts), None),
    )
    dtype = "uint8" if sample is None or sample.dtype == np.uint8 else "float32"
    length = 0 if sample is None else int(sample.shape[-1])
    return {
        "version": STATE_VERSION,
        "descriptor": {"dtype": dtype, "length": length},
        "next_track": assoc._next_track,
        "landmarks": [_landmark_doc(label, lm) for label, lm in assoc._landmarks.items()],
        "archived": [_landmark_doc(label, lm) for label, lm in assoc._archived.items()],
        "tracks": {
            robot: [
                {
                    "label": t.label,
                    "descriptor": _encode(t.descriptor),
                    "origin": [float(v) for v in t.origin],
                    "bearing": t.bearing,
                    "elevation": t.elevation,
                    "length": t.length,
                    "missed": t.missed,
                    "views": [
                        {"descriptor": _encode(d), "pose": [float(v) for v in p], "bearing": b}
                        for d, p, b in t.views
                    ],
                }
                for t in tracks
            ]
            for robot, tracks in assoc._tracks.items()
        },
    }


def _landmark_doc(label: str, lm: _Landmark) -> dict[str, Any]:
    return {
        "label": label,
        "descriptors": [_encode(d) for d in lm.descriptors],
        "view_angles": [float(a) for a in lm.view_angles],
        "height_m": lm.height_m,
        "height_n": lm.height_n,
        "lateral_m2": lm.lateral_m2,
        "lateral_n": lm.lateral_n,
    }


class _Reader:
    """Typed access to a JSON document with dotted-path errors."""

    def __init__(self, dtype: type[np.generic], length: int) -> None:
        self.dtype = dtype
        self.length = length

    @staticmethod
    def obj(value: Any, path: str) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise ValueError(f"{path}: must be an object")
        return value

    @staticmethod
    def lst(value: Any, path: str) -> list[Any]:
        if not isinstance(value, list):
            raise ValueError(f"{path}: must be an array")
        return value

    @staticmethod
    def num(value: Any, path: str) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"{path}: must be a number")
        if not math.isfinite(value):
            raise ValueError(f"{path}: must be finite")
        return float(value)

    @staticmethod
    def count(value: Any, path: str) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{path}: must be a non-negative integer")
        return value

    @staticmethod
    def label(value: Any, path: str) -> str:
        if not isinstance(value, str) or not value:
            raise ValueError(f"{path}: must be a non-empty string")
        return value

    def pose(self, value: Any, path: str) -> NDArray[np.float64]:
        items = self.lst(value, path)
        if len(items) != 3:
            raise ValueError(f"{path}: must be [x, y, theta]")
        return np.array([self.num(v, f"{path}[{i}]") for i, v in enumerate(items)])

    def descriptor(self, value: Any, path: str) -> NDArray[Any]:
        if not isinstance(value, str):
            raise ValueError(f"{path}: must be a base64 string")
        try:
            raw = base64.b64decode(value, validate=True)
        except (binascii.Error, ValueError) as exc:
            raise ValueError(f"{path}: not base64 ({exc})") from exc
        desc = np.frombuffer(raw, dtype=self.dtype).copy()
        if desc.shape != (self.length,):
            raise ValueError(
                f"{path}: {len(raw)} bytes, expected {self.length} {np.dtype(self.dtype).name}"
            )
        if not np.all(np.isfinite(desc.astype(np.float64))):
            raise ValueError(f"{path}: must be finite")
        return desc


def _read_landmark(r: _Reader, item: Any, path: str) -> tuple[str, _Landmark]:
    item = r.obj(item, path)
    label = r.label(item.get("label"), f"{path}.label")
    descs = r.lst(item.get("descriptors"), f"{path}.descriptors")
    angles = r.lst(item.get("view_angles"), f"{path}.view_angles")
    if len(descs) != len(angles) or not descs:
        raise ValueError(f"{path}: descriptors and view_angles: same non-zero length")
    height = item.get("height_m")
    return label, _Landmark(
        descriptors=[r.descriptor(d, f"{path}.descriptors[{k}]") for k, d in enumerate(descs)],
        view_angles=[r.num(a, f"{path}.view_angles[{k}]") for k, a in enumerate(angles)],
        height_m=None if height is None else r.num(height, f"{path}.height_m"),
        height_n=r.count(item.get("height_n"), f"{path}.height_n"),
        lateral_m2=max(0.0, r.num(item.get("lateral_m2", 0.0), f"{path}.lateral_m2")),
        lateral_n=max(0.0, r.num(item.get("lateral_n", 0.0), f"{path}.lateral_n")),
    )


def associator_from_doc(doc: Any, config: AssociationConfig | None = None) -> Associator:
    """An associator from `associator_to_doc`'s document; ValueError naming a bad field."""
    r = _Reader(np.uint8, 0)
    doc = r.obj(doc, "associator")
    if doc.get("version") != STATE_VERSION:
        raise ValueError(f"associator.version: must be {STATE_VERSION}")
    spec = r.obj(doc.get("descriptor"), "associator.descriptor")
    if spec.get("dtype") not in _DTYPES:
        raise ValueError(f"associator.descriptor.dtype: must be one of {sorted(_DTYPES)}")
    r = _Reader(_DTYPES[spec["dtype"]], r.count(spec.get("length"), "associator.descriptor.length"))
    out = Associator(config)
    out._next_track = r.count(doc.get("next_track"), "associator.next_track")
    for key in ("landmarks", "archived"):
        if key == "archived" and key not in doc:
            continue  # a document from before the archive of views
        into = out._landmarks if key == "landmarks" else out._archived
        for i, item in enumerate(r.lst(doc.get(key), f"associator.{key}")):
            label, lm = _read_landmark(r, item, f"associator.{key}[{i}]")
            into[label] = lm
    for robot, tracks in r.obj(doc.get("tracks"), "associator.tracks").items():
        kept: list[_Track] = []
        for i, item in enumerate(r.lst(tracks, f"associator.tracks.{robot}")):
            path = f"associator.tracks.{robot}[{i}]"
            item = r.obj(item, path)
            views = []
            for k, v in enumerate(r.lst(item.get("views"), f"{path}.views")):
                vp = f"{path}.views[{k}]"
                v = r.obj(v, vp)
                views.append(
                    (
                        r.descriptor(v.get("descriptor"), f"{vp}.descriptor"),
                        r.pose(v.get("pose"), f"{vp}.pose"),
                        r.num(v.get("bearing"), f"{vp}.bearing"),
                    )
                )
            kept.append(
                _Track(
                    label=r.label(item.get("label"), f"{path}.label"),
                    descriptor=r.descriptor(item.get("descriptor"), f"{path}.descriptor"),
                    origin=r.pose(item.get("origin"), f"{path}.origin"),
                    bearing=r.num(item.get("bearing"), f"{path}.bearing"),
                    elevation=r.num(item.get("elevation"), f"{path}.elevation"),
                    length=r.count(item.get("length"), f"{path}.length"),
                    missed=r.count(item.get("missed"), f"{path}.missed"),
                    views=views,
                )
            )
        out._tracks[robot] = kept
    return out
