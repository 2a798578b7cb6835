"""Point features on a panorama, spread over every direction, the wrap-around handled.

The panorama is cut into `bands` column bands; each band is padded on both sides
with the neighbouring columns, taken circularly (the columns right of the last
one are the first ones), and OpenCV's detector runs on the bands in a thread
pool (OpenCV releases the GIL). A band keeps only the keypoints whose column
falls inside its own (unpadded) range, so a feature that straddles the image's
edge is found exactly once, by one band, with its true column (taken modulo the
width). Then features are thinned per column bucket so that every direction is
represented.

Each feature's bearing and elevation follow `frontend.cameras.PanoramaCamera`.
"""

from __future__ import annotations

import itertools
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from frontend.cameras import PanoramaCamera

__all__ = ["FeatureConfig", "FeatureExtractor", "Features"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class FeatureConfig:
    """Detector parameters."""

    detector: str = "orb"
    """'orb' (binary descriptors, Hamming distance) or 'sift' (float, L2)."""
    max_features: int = 400
    """Most features kept per image."""
    bands: int = 4
    """Column bands detected independently (in parallel)."""
    buckets: int = 32
    """Column buckets for spreading: each keeps its share before the rest is filled."""
    pad_px: int = 64
    """Circular padding on each side of a band; must exceed the detector's border."""
    orb_levels: int = 3
    orb_scale: float = 1.2
    fast_threshold: int = 20
    subpixel: bool = True
    """Refine keypoints with cv2.cornerSubPix (the posters' corners: ~0.4 px better)."""
    min_corner_quality: float = 0.15
    """Smallest ratio of the structure tensor's eigenvalues (7x7 window at the refined
    position): a point on an edge (ratio near 0) has a bearing that slides with the
    viewpoint. 0 keeps every detection."""
    duplicate_px: float = 2.0
    """Detections closer than this to a stronger one are the same feature (dropped)."""
    sigma_px: float = 3.0
    """Bearing sigma of a level-0 feature, in pixels; grows with the pyramid scale. Larger
    than the corner error (~0.4 px): it also covers viewpoint-dependent corner shifts."""
    threads: int = 2
    upright: bool = True
    """ORB only: describe every feature at angle 0 instead of its intensity-centroid
    orientation. A panorama of a planar robot has no roll, so orientation invariance only
    hurts: it makes the four corners of a flat poster (rotations of one another) look
    alike. On rendered runs it halves how often a different corner within 10 deg is at
    least as close in Hamming distance as the same corner 8 frames later (16 % -> 8 %)."""

    def __post_init__(self) -> None:
        if self.detector not in ("orb", "sift"):
            raise ValueError("detector must be 'orb' or 'sift'")
        if self.max_features < 1 or self.bands < 1 or self.buckets < 1:
            raise ValueError("max_features, bands and buckets must be >= 1")
        if self.sigma_px <= 0:
            raise ValueError("sigma_px must be > 0")


@dataclass(frozen=True)
class Features:
    """N features of one panorama; every array has N rows.

    u, v: (N,) subpixel column and row (0-based pixel index, see PanoramaCamera).
    bearing_rad, elevation_rad, sigma_rad: (N,). response: (N,) detector score.
    octave: (N,) pyramid level. descriptors: (N, D) uint8 (ORB) or float32 (SIFT).
    """

    u: FloatArray
    v: FloatArray
    bearing_rad: FloatArray
    elevation_rad: FloatArray
    sigma_rad: FloatArray
    response: FloatArray
    octave: NDArray[np.int64]
    descriptors: NDArray[Any]
    binary: bool

    def __len__(self) -> int:
        return len(self.u)

    def subset(self, idx: NDArray[np.int64]) -> Features:
        return Features(
            self.u[idx],
            self.v[idx],
            self.bearing_rad[idx],
            self.elevation_rad[idx],
            self.sigma_rad[idx],
            self.response[idx],
            self.octave[idx],
            self.descriptors[idx],
            self.binary,
        )


class FeatureExtractor:
    """Detects and describes features on panoramas of one camera; reusable, thread-safe."""

    def __init__(self, camera: PanoramaCamera, config: FeatureConfig | None = None) -> None:
        self.camera = camera
        self.config = config or FeatureConfig()
        cfg = self.config
        if cfg.pad_px >= camera.width:
            raise ValueError("pad_px must be smaller than the panorama's width")
        edges = np.linspace(0, camera.width, cfg.bands + 1).round().astype(int)
        self._bands = [(int(a), int(b)) for a, b in itertools.pairwise(edges.tolist())]
        self._pool = ThreadPoolExecutor(max_workers=cfg.threads) if cfg.threads > 1 else None
        self._per_band = max(8, math.ceil(1.5 * cfg.max_features / cfg.bands))
        self._upright = cfg.upright and cfg.detector == "orb"

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False)

    def _detector(self) -> Any:
        cfg = self.config
        if cfg.detector == "sift":
            return cv2.SIFT.create(nfeatures=self._per_band)
        return cv2.ORB.create(
            nfeatures=self._per_band,
            scaleFactor=cfg.orb_scale,
            nlevels=cfg.orb_levels,
            fastThreshold=cfg.fast_threshold,
        )

    def _detect_band(
        self, padded: NDArray[np.uint8], band: tuple[int, int]
    ) -> tuple[list[Any], NDArray[Any] | None]:
        start, stop = band
        pad = self.config.pad_px
        strip = np.ascontiguousarray(padded[:, start : stop + 2 * pad])
        if self._upright:
            keypoints, desc = self._detector().detect(strip, None), None
        else:
            keypoints, desc = self._detector().detectAndCompute(strip, None)
            if desc is None:
                return [], None
        if not keypoints:
            return [], None
        keep = [i for i, kp in enumerate(keypoints) if pad <= kp.pt[0] < pad + stop - start]
        kept = [keypoints[i] for i in keep]
        for kp in kept:
            kp.pt = (kp.pt[0] - pad + start, kp.pt[1])
        return kept, None if desc is None else desc[keep]

    def _describe_upright(
        self, panorama: NDArray[np.uint8], u: FloatArray, v: FloatArray, octave: NDArray[np.int64]
    ) -> NDArray[np.uint8]:
        """(N, 32) upright binary descriptors (256 intensity comparisons, BRIEF-style) of
        features at (u, v) found on pyramid level `octave`.

        The comparisons are a fixed random pattern of point pairs in a 31 x 31 patch
        (Gaussian, as BRIEF's G II), scaled by the level's scale, on the panorama
        box-smoothed in proportion (5 x 5 at level 0); columns wrap around, rows are
        clamped. Not OpenCV's ORB
        descriptor (whose ``compute`` rebuilds and smooths a pyramid of the whole image,
        as costly as the detection), but the same kind and compared the same way
        (Hamming distance).
        """
        cfg = self.config
        h, w = panorama.shape
        reach = math.ceil(15 * cfg.orb_scale ** max(cfg.orb_levels - 1, 0)) + 2
        padded = np.concatenate([panorama[:, -reach:], panorama, panorama[:, :reach]], axis=1)
        out = np.zeros((len(u), 32), dtype=np.uint8)
        cu = np.rint(u).astype(np.int64) % w + reach
        cv = np.clip(np.rint(v).astype(np.int64), 0, h - 1)
        smoothed: dict[int, NDArray[np.uint8]] = {}  # by kernel size: levels 0 and 1 share 5
        for level in np.unique(octave).tolist():
            sel = np.flatnonzero(octave == level)
            scale = cfg.orb_scale**level
            k = 2 * round(2.0 * scale) + 1  # box smoothing: ~5x cheaper than a Gaussian
            if k not in smoothed:
                smoothed[k] = np.asarray(cv2.blur(padded, (k, k)), dtype=np.uint8)
            smooth = smoothed[k]
            off = np.rint(_BRIEF_PAIRS * scale).astype(np.int64)  # (256, 4)
            flat = smooth.ravel()
            stride = smooth.shape[1]
            y1 = np.clip(cv[sel, None] + off[None, :, 1], 0, h - 1)
            y2 = np.clip(cv[sel, None] + off[None, :, 3], 0, h - 1)
            i1 = y1 * stride + (cu[sel, None] + off[None, :, 0])
            i2 = y2 * stride + (cu[sel, None] + off[None, :, 2])
            out[sel] = np.packbits(flat[i1] < flat[i2], axis=1)  # (n, 32) from (n, 256)
        return out

    def extract(self, panorama: NDArray[np.uint8]) -> Features:
        """Features of one (height, width) uint8 panorama of this camera."""
        cam, cfg = self.camera, self.config
        if panorama.shape != cam.image_shape:
            raise ValueError(f"expected a {cam.image_shape} panorama, got {panorama.shape}")
        pad = cfg.pad_px
        padded = np.concatenate([panorama[:, -pad:], panorama, panorama[:, :pad]], axis=1)
        if self._pool is not None:
            results = list(self._pool.map(lambda b: self._detect_band(padded, b), self._bands))
        else:
            results = [self._detect_band(padded, b) for b in self._bands]
        keypoints = [kp for kps, _ in results for kp in kps]
        binary = cfg.detector == "orb"
        descs = (
            [np.zeros((len(keypoints), 32), dtype=np.uint8)]
            if self._upright
            else [d for _, d in results if d is not None]
        )
        if not keypoints:
            width = 32 if binary else 128
            dtype = np.uint8 if binary else np.float32
            return _empty(width, dtype, binary)
        octave = np.array([kp.octave & 0xFF for kp in keypoints], dtype=np.int64)
        octave = np.where(octave > 127, 0, octave)
        # OpenCV keypoints are pixel indices (centre at integer). ORB scales a level-l
        # index by s^l; a pixel centre of a resized level maps to (x_l + 0.5) s^l - 0.5.
        scale = cfg.orb_scale if binary else 2.0
        shift = 0.5 * (scale ** octave.astype(np.float64) - 1.0) if binary else 0.0
        u = np.mod(np.array([kp.pt[0] for kp in keypoints]) + shift, cam.width)
        v = np.array([kp.pt[1] for kp in keypoints]) + shift
        response = np.array([kp.response for kp in keypoints])
        if cfg.subpixel and self._pool is not None and len(u) > 1:
            # cornerSubPix releases the GIL: refine the halves in parallel (same result).
            parts = np.array_split(np.arange(len(u)), cfg.threads)
            refined = list(
                self._pool.map(lambda i: self._refine(panorama, u[i], v[i], octave[i]), parts)
            )
            u = np.concatenate([r[0] for r in refined])
            v = np.concatenate([r[1] for r in refined])
        elif cfg.subpixel:
            u, v = self._refine(panorama, u, v, octave)
        if cfg.min_corner_quality > 0:
            good = _corner_quality(panorama, u, v) >= cfg.min_corner_quality
            keypoints = [kp for kp, g in zip(keypoints, good.tolist(), strict=True) if g]
            u, v, response, octave = u[good], v[good], response[good], octave[good]
            descs = [np.concatenate(descs, axis=0)[good]]
            if not keypoints:
                return _empty(descs[0].shape[1], descs[0].dtype, binary)
        descriptors = np.concatenate(descs, axis=0)
        # ORB finds a corner on several pyramid levels: keep the strongest detection.
        unique = _suppress_duplicates(u, v, response, cam.width, self.config.duplicate_px)
        idx = unique[self._spread(u[unique], response[unique])]
        if self._upright:  # describe only the features kept
            descriptors[idx] = self._describe_upright(panorama, u[idx], v[idx], octave[idx])
        feats = Features(
            u=u,
            v=v,
            bearing_rad=cam.bearing_of_column(u),
            elevation_rad=cam.elevation_of_row(v),
            sigma_rad=cfg.sigma_px * cam.rad_per_px * scale ** octave.astype(np.float64),
            response=response,
            octave=octave,
            descriptors=descriptors,
            binary=binary,
        )
        return feats.subset(idx)

    def _refine(
        self, panorama: NDArray[np.uint8], u: FloatArray, v: FloatArray, octave: NDArray[np.int64]
    ) -> tuple[FloatArray, FloatArray]:
        """Subpixel corner positions (cv2.cornerSubPix on a circularly padded copy).

        The search window grows with the pyramid level the feature was found on.
        """
        pad = 16
        padded = np.concatenate([panorama[:, -pad:], panorama, panorama[:, :pad]], axis=1)
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 6, 0.03)
        ru, rv = u.copy(), v.copy()
        for level in np.unique(octave).tolist():
            sel = octave == level
            half = 3 + 2 * int(level)
            pts = np.column_stack([u[sel] + pad, v[sel]]).astype(np.float32).reshape(-1, 1, 2)
            ref = cv2.cornerSubPix(padded, pts, (half, half), (-1, -1), criteria).reshape(-1, 2)
            ru[sel] = ref[:, 0].astype(np.float64) - pad
            rv[sel] = ref[:, 1].astype(np.float64)
        # A refinement that wandered off (no corner there) keeps the detector's position.
        moved = np.hypot(ru - u, rv - v) > 3.0 + 2.0 * octave
        ru, rv = np.where(moved, u, ru), np.where(moved, v, rv)
        return np.mod(ru, self.camera.width), rv

    def _spread(self, u: FloatArray, response: FloatArray) -> NDArray[np.int64]:
        """Indices of at most max_features features: each column bucket's best first."""
        cfg = self.config
        n = len(u)
        if n <= cfg.max_features:
            return np.arange(n, dtype=np.int64)
        bucket = np.minimum((u * cfg.buckets / self.camera.width).astype(np.int64), cfg.buckets - 1)
        order = np.lexsort((-response, bucket))
        rank = np.empty(n, dtype=np.int64)
        first = np.searchsorted(bucket[order], np.arange(cfg.buckets))
        rank[order] = np.arange(n) - first[bucket[order]]
        # Round-robin over buckets: rank within bucket first, then response.
        chosen = np.lexsort((-response, rank))[: cfg.max_features]
        return np.sort(chosen).astype(np.int64)


def _corner_quality(panorama: NDArray[np.uint8], u: FloatArray, v: FloatArray) -> FloatArray:
    """(N,) lambda_min / lambda_max of the gradient structure tensor in a 7x7 window."""
    h, w = panorama.shape
    half = 4
    cu = np.rint(u).astype(np.int64)
    cv = np.clip(np.rint(v).astype(np.int64), half, h - half - 1)
    offs = np.arange(-half, half + 1)
    rows = (cv[:, None] + offs[None, :])[:, :, None]
    cols = np.mod(cu[:, None] + offs[None, :], w)[:, None, :]
    patch = panorama[rows, cols].astype(np.float64)  # (N, 9, 9)
    gx = 0.5 * (patch[:, 1:-1, 2:] - patch[:, 1:-1, :-2])
    gy = 0.5 * (patch[:, 2:, 1:-1] - patch[:, :-2, 1:-1])
    a = (gx * gx).sum(axis=(1, 2))
    b = (gx * gy).sum(axis=(1, 2))
    c = (gy * gy).sum(axis=(1, 2))
    root = np.sqrt(0.25 * (a - c) ** 2 + b * b)
    lmax = 0.5 * (a + c) + root
    lmin = 0.5 * (a + c) - root
    return np.where(lmax > 0, lmin / np.maximum(lmax, 1e-12), 0.0)


def _suppress_duplicates(
    u: FloatArray, v: FloatArray, response: FloatArray, width: int, radius: float
) -> NDArray[np.int64]:
    """Indices of detections with no stronger detection within `radius` px (columns wrap).

    Vectorised: detections sorted by column are compared with their next `_NEIGHBOURS`
    neighbours (plus the first columns again after the last, for the seam).
    """
    n = len(u)
    if n < 2:
        return np.arange(n, dtype=np.int64)
    order = np.argsort(u, kind="stable")
    wrap = order[u[order] < radius]
    idx = np.concatenate([order, wrap])
    us = np.concatenate([u[order], u[wrap] + width])
    vs = v[idx]
    drop = np.zeros(n, dtype=bool)
    for shift in range(1, min(_NEIGHBOURS, len(idx) - 1) + 1):
        close = (us[shift:] - us[:-shift] < radius) & (np.abs(vs[shift:] - vs[:-shift]) < radius)
        if not close.any():
            continue
        a, b = idx[:-shift][close], idx[shift:][close]
        weaker = np.where(response[a] < response[b], a, b)
        tie = (response[a] == response[b]) & (a != b)
        drop[weaker[a != b]] = True
        drop[np.maximum(a, b)[tie]] = True
    return np.flatnonzero(~drop).astype(np.int64)


_NEIGHBOURS = 32


def _brief_pairs(seed: int = 1103) -> NDArray[np.float64]:
    """(256, 4) point pairs (dx1, dy1, dx2, dy2) in pixels of a 31 x 31 patch: isotropic
    Gaussian with sigma 31 / 5 clipped to +-15 (BRIEF's G II); fixed by the seed, so
    descriptors stay comparable across runs and versions."""
    rng = np.random.default_rng(seed)
    return np.clip(np.round(rng.normal(0.0, 31.0 / 5.0, size=(256, 4))), -15, 15)


_BRIEF_PAIRS = _brief_pairs()


def _empty(width: int, dtype: Any, binary: bool) -> Features:
    z = np.zeros(0)
    return Features(
        z, z, z, z, z, z, np.zeros(0, dtype=np.int64), np.zeros((0, width), dtype=dtype), binary
    )
