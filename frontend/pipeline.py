"""The front end of one map: image bytes (or pixels) in, labelled bearing observations out.

`FrontEnd` = camera model + image validation + feature extraction + association.
It knows nothing of HTTP or of the estimator: the caller gives the predicted
pose, its covariance and the live landmarks, and reports back after the
estimator processed the frame (`commit`).
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from frontend.association import Association, AssociationConfig, Associator, LandmarkEstimate
from frontend.cameras import CameraModel, OmniCamera, PanoramaCamera
from frontend.errors import WrongImageSize
from frontend.features import FeatureConfig, FeatureExtractor, Features
from frontend.image_io import MAX_IMAGE_BYTES, MAX_IMAGE_PIXELS, decode_image, image_for_camera

__all__ = ["FrontEnd"]


class FrontEnd:
    """Images of one map's camera -> features -> labelled observations."""

    def __init__(
        self,
        camera: CameraModel,
        *,
        features: FeatureConfig | None = None,
        association: AssociationConfig | None = None,
        max_bytes: int = MAX_IMAGE_BYTES,
        max_pixels: int = MAX_IMAGE_PIXELS,
    ) -> None:
        self.camera = camera
        self.panorama_camera: PanoramaCamera = (
            camera.panorama if isinstance(camera, OmniCamera) else camera
        )
        self.extractor = FeatureExtractor(self.panorama_camera, features)
        self.associator = Associator(association)
        self.max_bytes = max_bytes
        self.max_pixels = max_pixels

    def close(self) -> None:
        self.extractor.close()

    def panorama(self, image: bytes | NDArray[np.uint8]) -> NDArray[np.uint8]:
        """Decode (bytes) and validate an image; an omni ring is unwrapped.

        Raises a frontend.errors.ImageError (status 422 or 413) for a bad image.
        """
        if isinstance(image, bytes | bytearray | memoryview):
            pixels = decode_image(
                bytes(image), max_bytes=self.max_bytes, max_pixels=self.max_pixels
            )
        else:
            pixels = np.asarray(image)
            if pixels.ndim == 3 and pixels.shape[2] == 1:
                pixels = pixels[:, :, 0]
            if pixels.dtype != np.uint8:
                raise WrongImageSize(f"expected 8-bit pixels, got {pixels.dtype}")
        return image_for_camera(pixels, self.camera)

    def features(self, image: bytes | NDArray[np.uint8]) -> Features:
        """Features of one image (validated and unwrapped first)."""
        return self.extractor.extract(self.panorama(image))

    def observe(
        self,
        image: bytes | NDArray[np.uint8] | Features,
        *,
        robot: str,
        predicted_pose: ArrayLike,
        pose_cov: ArrayLike | None,
        landmarks: Mapping[str, LandmarkEstimate],
    ) -> Association:
        """Label one frame's features; `association.observations` go to the estimator.

        Nothing changes until `commit` (a refused frame leaves the front end as it was).
        """
        feats = image if isinstance(image, Features) else self.features(image)
        return self.associator.associate(
            feats,
            robot=robot,
            predicted_pose=predicted_pose,
            pose_cov=pose_cov,
            landmarks=landmarks,
        )

    def commit(
        self,
        association: Association,
        *,
        pose: ArrayLike,
        live_labels: Collection[str],
        landmark_xy: Mapping[str, ArrayLike] | None = None,
        removed_labels: Collection[str] = (),
    ) -> None:
        """Record what the estimator made of the frame (see Associator.commit)."""
        self.associator.commit(
            association,
            pose=pose,
            live_labels=live_labels,
            landmark_xy=landmark_xy,
            removed_labels=removed_labels,
        )

    def describe(self) -> dict[str, Any]:
        return {"camera": self.camera.as_config()}
