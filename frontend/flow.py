"""Optical flow: last frame's tracked features carried into this frame's panorama.

The detector finds only about half of the visible corners in any one frame (rendered
runs: 51 % within 2 px at 400 features), so a candidate track whose corner is missed
for a few frames ends, and the corner comes back under a new label: 5.8 labels per
corner over a 1000-frame run, half of all corner observations under labels that never
became landmarks. Pyramidal Lucas-Kanade (cv2.calcOpticalFlowPyrLK) follows each
feature the associator used in the robot's last frame (a landmark match or a track)
from that panorama into this one, whether or not the detector fires there again; the
followed points join this frame's detections as features of their own (described at
their new position), and the association treats them like any other feature, with the
same gates, descriptor limit and ratio tests.

Wrap-around: both panoramas are padded with `pad_px` columns taken circularly, and this
frame's is first rolled by the predicted turn (whole columns), so a rotation in place
leaves the points where they were and a point near the seam stays inside the padding.

Convention: columns and rows as `frontend.cameras.PanoramaCamera` (u to the right,
bearing ``wrap(pi - 2 pi (u + 0.5) / width)``); a turn of the robot by +dtheta (CCW)
moves every column by ``+dtheta / rad_per_px`` (to the right).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from frontend.features import FeatureExtractor, Features, corner_quality

__all__ = ["FlowConfig", "FlowSeed", "carry_features"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class FlowConfig:
    """Lucas-Kanade parameters (pixels)."""

    enabled: bool = False
    """Off: on rendered runs it made the ATE worse (see the README)."""
    follow: str = "all"
    """What is followed: "all" features the associator used (landmark matches, tracks,
    new tracks) or "landmarks" (landmark matches only)."""
    new_tracks: bool = True
    """A followed point no landmark or track took may start a new track."""
    window_px: int = 15
    max_level: int = 3
    """Pyramid levels above the image (3: motions up to ~8 window widths)."""
    max_round_trip_px: float = 0.5
    """A point tracked forward and then back must land this close to where it started."""
    duplicate_px: float = 3.0
    """A followed point this close to a detection (or a stronger followed point) is the
    same feature: the detection is kept."""
    pad_px: int = 48
    border_px: int = 16
    """Rows this close to the top or bottom are dropped (the descriptor's patch)."""


@dataclass(frozen=True)
class FlowSeed:
    """What a robot's next frame follows: its last committed panorama and the features
    of it the associator used (landmark matches and tracks), and the heading (rad) the
    estimator gave that frame."""

    panorama: NDArray[np.uint8]
    u: FloatArray
    v: FloatArray
    octave: NDArray[np.int64]
    response: FloatArray
    theta: float


def _pad(image: NDArray[np.uint8], pad: int) -> NDArray[np.uint8]:
    return np.ascontiguousarray(np.concatenate([image[:, -pad:], image, image[:, :pad]], axis=1))


def carry_features(
    seed: FlowSeed,
    panorama: NDArray[np.uint8],
    turn_rad: float,
    detections: Features,
    extractor: FeatureExtractor,
    config: FlowConfig | None = None,
) -> Features:
    """`detections` plus the seed's features followed into `panorama` (appended after
    them; same fields), given the robot's predicted turn since the seed's frame."""
    cfg = config or FlowConfig()
    cam = extractor.camera
    h, w = panorama.shape
    if len(seed.u) == 0 or seed.panorama.shape != panorama.shape or not extractor.upright:
        return detections
    shift = round(turn_rad / cam.rad_per_px)
    pad = cfg.pad_px
    before = _pad(seed.panorama, pad)
    after = _pad(np.roll(panorama, -shift, axis=1), pad)
    start = np.column_stack([seed.u + pad, seed.v]).astype(np.float32).reshape(-1, 1, 2)
    win = (cfg.window_px, cfg.window_px)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.03)
    moved, ok, _ = cv2.calcOpticalFlowPyrLK(
        before, after, start, None, winSize=win, maxLevel=cfg.max_level, criteria=criteria
    )
    back, ok_back, _ = cv2.calcOpticalFlowPyrLK(
        after, before, moved, None, winSize=win, maxLevel=cfg.max_level, criteria=criteria
    )
    moved, back = moved.reshape(-1, 2).astype(np.float64), back.reshape(-1, 2).astype(np.float64)
    round_trip = np.hypot(back[:, 0] - start[:, 0, 0], back[:, 1] - start[:, 0, 1])
    keep = (
        (ok.ravel() == 1)
        & (ok_back.ravel() == 1)
        & (round_trip <= cfg.max_round_trip_px)
        & (moved[:, 0] >= 0)
        & (moved[:, 0] < w + 2 * pad)
        & (moved[:, 1] >= cfg.border_px)
        & (moved[:, 1] < h - cfg.border_px)
    )
    idx = np.flatnonzero(keep)
    u = np.mod(moved[idx, 0] - pad + shift, w)
    v = moved[idx, 1]
    octave, response = seed.octave[idx], seed.response[idx]
    min_quality = extractor.config.min_corner_quality
    if min_quality > 0 and len(idx):
        good = corner_quality(panorama, u, v) >= min_quality
        u, v, octave, response = u[good], v[good], octave[good], response[good]
    # Not where a detection already is, nor on a stronger followed point.
    fresh = _away_from(u, v, detections.u, detections.v, w, cfg.duplicate_px)
    order = np.argsort(-response[fresh], kind="stable")
    chosen: list[int] = []
    for i in fresh[order].tolist():
        if chosen:
            du = np.abs(np.mod(u[chosen] - u[i] + w / 2, w) - w / 2)
            if np.any((du < cfg.duplicate_px) & (np.abs(v[chosen] - v[i]) < cfg.duplicate_px)):
                continue
        chosen.append(i)
    sel = np.sort(np.array(chosen, dtype=np.int64))
    if len(sel) == 0:
        return detections
    u, v, octave, response = u[sel], v[sel], octave[sel], response[sel]
    descriptors = extractor.describe(panorama, u, v, octave)
    carried = extractor.features_at(u, v, octave, response, descriptors)
    return _concat(detections, carried)


def _away_from(
    u: FloatArray, v: FloatArray, du_ref: FloatArray, dv_ref: FloatArray, w: int, radius: float
) -> NDArray[np.int64]:
    """Indices of points (u, v) with no reference point within `radius` (columns wrap)."""
    if len(du_ref) == 0 or len(u) == 0:
        return np.arange(len(u), dtype=np.int64)
    du = np.abs(np.mod(u[:, None] - du_ref[None, :] + w / 2, w) - w / 2)
    near = (du < radius) & (np.abs(v[:, None] - dv_ref[None, :]) < radius)
    return np.flatnonzero(~near.any(axis=1)).astype(np.int64)


def _concat(a: Features, b: Features) -> Features:
    return Features(
        u=np.concatenate([a.u, b.u]),
        v=np.concatenate([a.v, b.v]),
        bearing_rad=np.concatenate([a.bearing_rad, b.bearing_rad]),
        elevation_rad=np.concatenate([a.elevation_rad, b.elevation_rad]),
        sigma_rad=np.concatenate([a.sigma_rad, b.sigma_rad]),
        response=np.concatenate([a.response, b.response]),
        octave=np.concatenate([a.octave, b.octave]),
        descriptors=np.concatenate([a.descriptors, b.descriptors], axis=0),
        binary=a.binary,
    )
