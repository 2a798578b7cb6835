"""Small hand-made images and scenes shared by the front-end tests."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
from numpy.typing import NDArray

from service.offline.datasets.indoor_sim import make_world
from service.offline.datasets.render import TexturedWorld, make_textured_world


def blank(height: int, width: int, level: int = 90) -> NDArray[np.uint8]:
    return np.full((height, width), level, dtype=np.uint8)


def paint_corner(image: NDArray[np.uint8], column: int, row: int, size: int = 24) -> None:
    """A bright square whose top-left corner is the pixel corner left of (column, row);
    columns wrap around."""
    width = image.shape[1]
    cols = np.arange(column, column + size) % width
    image[row : row + size][:, cols] = 230


def small_world(seed: int = 3) -> TexturedWorld:
    rng = np.random.default_rng(seed)
    return make_textured_world(make_world(rooms=(2, 1), landmarks=2, rng=rng), rng=rng)


def png(image: NDArray[np.uint8]) -> bytes:
    """`image` encoded as PNG."""
    ok, buf = cv2.imencode(".png", image)
    assert ok
    return bytes(buf.tobytes())


def png_header_only(width: int, height: int) -> bytes:
    """A PNG signature and IHDR chunk claiming the given size, no pixel data (the first
    bytes of a decompression bomb)."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    chunk = b"IHDR" + ihdr
    return (
        b"\x89PNG\r\n\x1a\n"
        + struct.pack(">I", len(ihdr))
        + chunk
        + struct.pack(">I", zlib.crc32(chunk) & 0xFFFFFFFF)
    )
