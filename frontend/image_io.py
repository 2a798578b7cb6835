"""Image bytes in, a validated grayscale panorama out.

Checks happen cheapest first: byte count, magic number, the header's
dimensions (read without decoding the pixels, so a decompression bomb is
refused before it is inflated), then the decode itself, then the camera's
expected size.
"""

from __future__ import annotations

import struct

import cv2
import numpy as np
from numpy.typing import NDArray

from frontend.cameras import CameraModel, OmniCamera
from frontend.errors import (
    EmptyImage,
    ImageTooLarge,
    UndecodableImage,
    WrongImageSize,
)

__all__ = ["MAX_IMAGE_BYTES", "MAX_IMAGE_PIXELS", "decode_image", "image_for_camera", "png_size"]

MAX_IMAGE_BYTES = 16 * 2**20
"""Default largest encoded image, bytes."""
MAX_IMAGE_PIXELS = 16 * 2**20
"""Default largest decoded image, pixels (rows x columns)."""

_PNG = b"\x89PNG\r\n\x1a\n"
_JPEG = b"\xff\xd8\xff"


def png_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR chunk, or None if the header is not readable."""
    if len(data) < 24 or data[:8] != _PNG or data[12:16] != b"IHDR":
        return None
    width, height = struct.unpack(">II", data[16:24])
    return int(width), int(height)


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a JPEG's first SOF marker, or None."""
    i = 2
    n = len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        length = int.from_bytes(data[i + 2 : i + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if i + 9 > n:
                return None
            height = int.from_bytes(data[i + 5 : i + 7], "big")
            width = int.from_bytes(data[i + 7 : i + 9], "big")
            return width, height
        i += 2 + length
    return None


def decode_image(
    data: bytes,
    *,
    max_bytes: int = MAX_IMAGE_BYTES,
    max_pixels: int = MAX_IMAGE_PIXELS,
) -> NDArray[np.uint8]:
    """Decode PNG or JPEG bytes to an (H, W) uint8 grayscale image.

    Raises:
        EmptyImage: no bytes, or zero rows or columns.
        ImageTooLarge: more than `max_bytes` bytes or `max_pixels` pixels (413).
        UndecodableImage: not a PNG/JPEG, or OpenCV cannot decode it.
    """
    if not data:
        raise EmptyImage("the image is empty (0 bytes)")
    if len(data) > max_bytes:
        raise ImageTooLarge(f"the image has {len(data)} bytes; at most {max_bytes} are accepted")
    if data.startswith(_PNG):
        size = png_size(data)
    elif data.startswith(_JPEG):
        size = _jpeg_size(data)
    else:
        raise UndecodableImage("the image is neither PNG nor JPEG (unknown magic number)")
    if size is not None:
        width, height = size
        if width == 0 or height == 0:
            raise EmptyImage(f"the image has zero size ({width}x{height})")
        if width * height > max_pixels:
            raise ImageTooLarge(
                f"the image has {width}x{height} pixels; at most {max_pixels} are accepted"
            )
    buf = np.frombuffer(data, dtype=np.uint8)
    try:
        image = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    except cv2.error as exc:
        raise UndecodableImage(f"the image could not be decoded: {exc}") from exc
    if image is None:
        raise UndecodableImage("the image could not be decoded (corrupt or truncated data)")
    if image.size == 0:
        raise EmptyImage("the image has zero size")
    if image.size > max_pixels:
        raise ImageTooLarge(
            f"the image has {image.shape[1]}x{image.shape[0]} pixels; "
            f"at most {max_pixels} are accepted"
        )
    return np.asarray(image, dtype=np.uint8)


def image_for_camera(image: NDArray[np.uint8], camera: CameraModel) -> NDArray[np.uint8]:
    """Check an (H, W) grayscale image against the camera; return the panorama to analyse.

    An omni ring is unwrapped (OmniCamera.unwrap); a panorama is returned as is.

    Raises:
        EmptyImage: zero rows or columns.
        WrongImageSize: the dimensions are not the camera's.
    """
    if image.ndim != 2:
        raise WrongImageSize(f"expected a single-channel image, got shape {image.shape}")
    if image.size == 0:
        raise EmptyImage("the image has zero size")
    rows, cols = camera.image_shape
    if image.shape != (rows, cols):
        raise WrongImageSize(
            f"the map's {camera.kind} camera expects {cols}x{rows} pixels (width x height), "
            f"got {image.shape[1]}x{image.shape[0]}"
        )
    if isinstance(camera, OmniCamera):
        return camera.unwrap(image)
    return image
