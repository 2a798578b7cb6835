"""Typed errors of the front end. The API maps `status` to its HTTP answer (422 or 413)."""

from __future__ import annotations


class ImageError(ValueError):
    """An image was refused before anything in the map changed.

    `status` is the HTTP status the API should answer with; `detail` says what
    was wrong, in words a client can act on.
    """

    status = 422

    def __init__(self, detail: str) -> None:
        super().__init__(detail)
        self.detail = detail


class UndecodableImage(ImageError):
    """The bytes are not a PNG or JPEG that OpenCV can decode."""


class EmptyImage(ImageError):
    """No bytes, or an image with zero rows or columns."""


class WrongImageSize(ImageError):
    """The image's dimensions are not the ones the map's camera expects."""


class ImageTooLarge(ImageError):
    """More bytes or pixels than the configured limits allow (HTTP 413)."""

    status = 413
