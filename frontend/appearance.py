"""Whole-panorama appearance signatures for place recognition, yaw-invariant.

A signature is the panorama's log intensity, area-averaged down to a coarse grid of
``bands`` elevation bands x ``columns`` bearing columns, each band normalised to zero
mean and unit variance. The log turns a change of illumination gain into an offset
and a change of gamma into a scale, and the per-band normalisation removes both; the
averaging keeps the signature smooth over a few centimetres of position.

Matching a query against a place's signature is a circular cross-correlation over the
columns (one FFT per signature): a rotation of the robot is a column shift of its
panorama, so the best shift is the yaw offset and its correlation the score (the mean
normalised cross-correlation over the bands, in [-1, 1]).

Convention (the panorama's, frontend.cameras.PanoramaCamera): column u looks at
bearing ``wrap(pi - 2 pi (u + 0.5) / W)``, so bearings grow towards column 0. A robot
turned by ``+delta`` (counter-clockwise) sees every wall point ``delta`` further
clockwise, i.e. ``delta * W / 2pi`` columns further right: the query's signature is
the reference's shifted right by ``k = delta * columns / 2pi`` columns, and
``match`` returns ``yaw_offset_rad = wrap(2 pi k / columns)`` = query yaw - place yaw.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from graph.angles import wrap_angles

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class SignatureConfig:
    columns: int = 256
    """Bearing columns of a signature (yaw resolution 2 pi / columns)."""
    bands: int = 8
    """Elevation bands (rows) of a signature."""

    def __post_init__(self) -> None:
        if self.columns < 8 or self.bands < 1:
            raise ValueError("a signature needs at least 8 columns and 1 band")


_LOG1P = np.log1p(np.arange(256, dtype=np.float32)).reshape(1, 256)
"""log(1 + i) of every 8-bit intensity, float32 (a lookup table for `signature`)."""


def signature(
    panorama: NDArray[np.uint8], config: SignatureConfig | None = None
) -> NDArray[np.float32]:
    """``(bands, columns)`` signature of a grayscale panorama ``(H, W)`` (see the module
    docstring). A band without contrast is all zeros."""
    cfg = config or SignatureConfig()
    if panorama.dtype != np.uint8:
        raise ValueError(f"panorama must be 8-bit grayscale, got {panorama.dtype}")
    if panorama.ndim != 2 or panorama.shape[1] < cfg.columns or panorama.shape[0] < cfg.bands:
        raise ValueError(
            f"panorama must be a 2-D image at least {cfg.columns} wide and {cfg.bands} high, "
            f"got shape {panorama.shape}"
        )
    log_i = cv2.LUT(panorama, _LOG1P)  # = np.log1p(panorama.astype(np.float32)), 3x cheaper
    small = cv2.resize(log_i, (cfg.columns, cfg.bands), interpolation=cv2.INTER_AREA)
    small -= small.mean(axis=1, keepdims=True)
    std = small.std(axis=1, keepdims=True)
    return np.divide(small, std, out=np.zeros_like(small), where=std > 1e-6)


@dataclass(frozen=True, slots=True)
class AppearanceMatch:
    """Scores ``(P,)`` of every place (NCC in [-1, 1]) and the yaw offsets ``(P,)``
    (query yaw - place yaw, radians) at which they were found; ``order`` best first."""

    scores: FloatArray
    yaw_offsets_rad: FloatArray

    @property
    def order(self) -> NDArray[np.int64]:
        return np.argsort(-self.scores, kind="stable").astype(np.int64)


class AppearanceIndex:
    """The places' signatures with their spectra precomputed: a query costs one FFT of
    its own and one product + inverse FFT per place (vectorised over places)."""

    def __init__(self, config: SignatureConfig | None = None) -> None:
        self.config = config or SignatureConfig()
        c = self.config
        self._spectra = np.zeros((0, c.bands, c.columns // 2 + 1), dtype=np.complex128)

    def __len__(self) -> int:
        return int(self._spectra.shape[0])

    def add(self, place_signature: NDArray[np.float32]) -> int:
        """Add a place's signature; returns its index."""
        sig = np.asarray(place_signature, dtype=np.float64)
        if sig.shape != (self.config.bands, self.config.columns):
            raise ValueError(f"signature shape {sig.shape} does not match the index's config")
        spectrum = np.fft.rfft(sig, axis=1)
        self._spectra = np.concatenate([self._spectra, spectrum[None]], axis=0)
        return len(self) - 1

    def match(self, query_signature: NDArray[np.float32]) -> AppearanceMatch:
        """Score every place against a query signature at every column shift."""
        c = self.config
        q = np.fft.rfft(np.asarray(query_signature, dtype=np.float64), axis=1)
        if len(self) == 0:
            return AppearanceMatch(np.zeros(0), np.zeros(0))
        # corr[p, k] = sum_b sum_c q[b, c + k] r[p, b, c]  (circular)
        cross = np.fft.irfft(np.sum(q[None] * np.conj(self._spectra), axis=1), n=c.columns)
        cross /= c.bands * c.columns
        shift = np.argmax(cross, axis=1)
        scores = cross[np.arange(len(self)), shift]
        yaw = wrap_angles(2.0 * math.pi * shift / c.columns)
        return AppearanceMatch(scores.astype(np.float64), np.asarray(yaw))


def rotation_between(
    previous: NDArray[np.float32], current: NDArray[np.float32]
) -> tuple[float, float]:
    """(yaw change rad, score): how far the robot turned from the panorama whose
    signature is `previous` to the one whose signature is `current` (current yaw -
    previous yaw, as AppearanceIndex.match's offset), refined to a fraction of a column
    by a parabola through the correlation peak and its two neighbours; the score is the
    normalised cross-correlation at the best whole-column shift, in [-1, 1]. Both
    signatures ``(bands, columns)`` of one config (a visual compass: a rotation of a
    panorama is a column shift)."""
    a = np.asarray(previous, dtype=np.float64)
    b = np.asarray(current, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2:
        raise ValueError(f"signatures of different shapes: {a.shape} and {b.shape}")
    bands, columns = a.shape
    spectrum = np.sum(np.fft.rfft(b, axis=1) * np.conj(np.fft.rfft(a, axis=1)), axis=0)
    cross = np.fft.irfft(spectrum, n=columns) / (bands * columns)
    k = int(np.argmax(cross))
    left, mid, right = cross[(k - 1) % columns], cross[k], cross[(k + 1) % columns]
    curvature = left - 2.0 * mid + right
    frac = 0.5 * (left - right) / curvature if curvature < 0 else 0.0
    yaw = float(wrap_angles(np.asarray(2.0 * math.pi * (k + frac) / columns)))
    return yaw, float(mid)
