"""Every bad image is a typed error with the HTTP status the API answers; good ones decode."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from frontend.cameras import OmniCamera, PanoramaCamera
from frontend.errors import (
    EmptyImage,
    ImageError,
    ImageTooLarge,
    UndecodableImage,
    WrongImageSize,
)
from frontend.image_io import decode_image, image_for_camera
from frontend.pipeline import FrontEnd
from tests.frontend._synthetic import png, png_header_only

CAM = PanoramaCamera(256, 64)


def test_good_png_and_jpeg_decode_to_grayscale() -> None:
    rng = np.random.default_rng(0)
    colour = rng.integers(0, 255, (64, 256, 3), dtype=np.uint8)
    for ext in (".png", ".jpg"):
        ok, buf = cv2.imencode(ext, colour)
        assert ok
        image = decode_image(buf.tobytes())
        assert image.shape == (64, 256) and image.dtype == np.uint8
        assert image_for_camera(image, CAM) is image


@pytest.mark.parametrize(
    ("data", "error", "status"),
    [
        (b"", EmptyImage, 422),
        (b"hello, this is not an image at all", UndecodableImage, 422),
        (b"GIF89a" + bytes(100), UndecodableImage, 422),
        (png_header_only(0, 64), EmptyImage, 422),
        (png_header_only(256, 0), EmptyImage, 422),
        (png_header_only(100_000, 100_000), ImageTooLarge, 413),
        (png_header_only(256, 64), UndecodableImage, 422),  # header, no pixels
    ],
)
def test_bad_bytes(data: bytes, error: type[ImageError], status: int) -> None:
    with pytest.raises(error) as info:
        decode_image(data)
    assert info.value.status == status
    assert info.value.detail


def test_truncated_png_is_undecodable() -> None:
    data = png(np.random.default_rng(1).integers(0, 255, (64, 256), dtype=np.uint8))
    with pytest.raises(UndecodableImage):
        decode_image(data[: len(data) // 2])


def test_too_many_bytes_is_413() -> None:
    data = png(np.zeros((64, 256), dtype=np.uint8))
    with pytest.raises(ImageTooLarge) as info:
        decode_image(data, max_bytes=len(data) - 1)
    assert info.value.status == 413


def test_too_many_pixels_is_413() -> None:
    data = png(np.zeros((64, 256), dtype=np.uint8))
    with pytest.raises(ImageTooLarge):
        decode_image(data, max_pixels=64 * 256 - 1)


@pytest.mark.parametrize("shape", [(64, 255), (65, 256), (256, 64)])
def test_wrong_dimensions_for_the_camera(shape: tuple[int, int]) -> None:
    with pytest.raises(WrongImageSize, match="expects 256x64") as info:
        image_for_camera(np.zeros(shape, dtype=np.uint8), CAM)
    assert info.value.status == 422


def test_wrong_dimensions_for_an_omni_camera() -> None:
    omni = OmniCamera(200, 200, (100.0, 100.0), 20.0, 90.0, pano_width=256, pano_height=64)
    # A panorama-sized image is not the ring the omni camera expects.
    with pytest.raises(WrongImageSize):
        image_for_camera(np.zeros((64, 256), dtype=np.uint8), omni)
    assert image_for_camera(np.zeros((200, 200), dtype=np.uint8), omni).shape == (64, 256)


def test_front_end_refuses_bad_images_and_stays_unchanged() -> None:
    fe = FrontEnd(CAM)
    before = (fe.associator.known_landmarks, fe.associator.track_count("r1"))
    for data in (b"", b"junk", png(np.zeros((10, 10), dtype=np.uint8))):
        with pytest.raises(ImageError):
            fe.observe(data, robot="r1", predicted_pose=(0, 0, 0), pose_cov=None, landmarks={})
    with pytest.raises(WrongImageSize):
        fe.features(np.zeros((64, 256), dtype=np.float32))
    assert (fe.associator.known_landmarks, fe.associator.track_count("r1")) == before
    fe.close()
