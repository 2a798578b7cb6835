"""Image frames of one camera map, inside its session (worker process).

`MapVision` holds the map's front end (camera, features, association), which the
map pipeline ties to the estimator. An image frame's decoding, validation and feature
extraction run in a helper thread (`extract`; OpenCV releases the GIL) while the
session checks the frame and appends it, image included, to the durable log; the
session then waits for them (`features_of`). A frame that waits behind the current
one has its features extracted meanwhile (`prefetch` from the worker's reader thread,
`take` in its own `submit`). A refused image (frontend.errors.ImageError) becomes a
422 or 413 problem (`image_refused`).

Its state between frames (the associator's landmark views and candidate tracks)
is the map pipeline's (service.pipeline), and travels with its snapshots.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np
from numpy.typing import NDArray

from frontend.appearance import signature
from frontend.errors import ImageError
from frontend.features import Features
from frontend.pipeline import FrontEnd
from graph.errors import InvalidFrame
from graph.types import FrameInput
from service.errors import ServiceError
from service.frames_io import observations_json
from service.pipeline import FrameStep, ImageFeatures, MapPipeline
from service.pipeline.config import camera_model

PREFETCH_LIMIT = 8
"""Most images whose features are extracted ahead of their frame."""

Pending = Future[tuple[Features, NDArray[np.float32], float, float]]
"""Features of one image being extracted, with its appearance signature and the
decoding's and the extraction's milliseconds."""


def image_refused(exc: ImageError) -> ServiceError:
    """The API's answer to a refused image: 413 (too large) or 422, naming the part."""
    if exc.status == 413:
        return ServiceError(413, "image-too-large", "Image too large", f"image: {exc.detail}")
    return ServiceError(
        422, "invalid-image", "Invalid image", f"image: {exc.detail}", field="image"
    )


def no_camera(map_id: str) -> ServiceError:
    return ServiceError(
        422,
        "no-camera",
        "Map has no camera",
        f"image: map {map_id!r} was created without a camera (config.camera is null), so it "
        "takes bearing observations only; create the map with e.g. "
        '"camera": {"model": "panorama", "width": 2048, "height": 512}',
        field="image",
    )


class MapVision:
    """One camera map's front end next to its estimator."""

    def __init__(self, front_end: FrontEnd) -> None:
        self.front_end = front_end
        self._threads = ThreadPoolExecutor(max_workers=1, thread_name_prefix="covslam-features")
        self._prefetched: dict[bytes, Pending] = {}
        self._lock = threading.Lock()
        """Guards `_prefetched`: the worker's reader thread prefetches, its main thread takes."""

    @classmethod
    def for_config(cls, config: dict[str, Any]) -> MapVision | None:
        """The front end of a stored map config; None for a map without a camera."""
        camera = camera_model(config)
        return None if camera is None else cls(FrontEnd(camera))

    def close(self) -> None:
        self._threads.shutdown(wait=True)
        self.front_end.close()

    def check(self, frame: FrameInput) -> None:
        """Refuse what the front end cannot predict from (before anything is logged)."""
        if frame.observations:
            raise InvalidFrame(
                "meta.observations",
                "must be absent in an image frame: the image's features are the observations",
            )

    def check_localisable(self, frame: FrameInput, *, known: bool) -> None:
        """A robot the map does not know yet (`known` False) without initial_pose is
        localised by matching its images to the landmarks' stored views: refused while
        the map holds none."""
        if frame.initial_pose is None and not known and not self.front_end.associator.has_views():
            raise InvalidFrame(
                "meta.initial_pose",
                f"robot {frame.robot!r} has sent no frame to this map yet, and the map has "
                "no landmarks to localise it against; its first image frame needs "
                "initial_pose",
            )

    def extract(self, image: bytes) -> Pending:
        """Decode, validate and describe `image` in the helper thread."""

        def run() -> tuple[Features, NDArray[np.float32], float, float]:
            return self._features(image)

        return self._threads.submit(run)

    def _features(self, image: bytes) -> tuple[Features, NDArray[np.float32], float, float]:
        """(features, appearance signature, decode ms (with validation and an omni
        unwrap), extraction ms (features and signature)): one decode."""
        t0 = time.perf_counter()
        panorama = self.front_end.panorama(image)
        t1 = time.perf_counter()
        features = self.front_end.extractor.extract(panorama)
        sig = signature(panorama)
        return features, sig, 1e3 * (t1 - t0), 1e3 * (time.perf_counter() - t1)

    def prefetch(self, image: bytes) -> None:
        """Start extracting the features of a frame that waits behind the current one."""
        with self._lock:
            if image in self._prefetched:
                return
            while len(self._prefetched) >= PREFETCH_LIMIT:
                self._prefetched.pop(next(iter(self._prefetched)))
            self._prefetched[image] = self.extract(image)

    def take(self, image: bytes) -> Pending | None:
        """The prefetched extraction of `image`, if `prefetch` started one."""
        with self._lock:
            return self._prefetched.pop(image, None)

    def features_of(
        self, image: Pending | bytes
    ) -> tuple[Features, NDArray[np.float32], dict[str, float]]:
        """(features, appearance signature, timings ms: decode, features, features_wait)
        of an image (extracted now, or by `extract` / `prefetch`). Raises ImageError for
        a refused image."""
        t0 = time.perf_counter()
        if isinstance(image, bytes):
            features, sig, decode_ms, extract_ms = self._features(image)
        else:
            features, sig, decode_ms, extract_ms = image.result()
        waited_ms = 1e3 * (time.perf_counter() - t0)
        return (
            features,
            sig,
            {"decode": decode_ms, "features": extract_ms, "features_wait": waited_ms},
        )

    def step(
        self, pipeline: MapPipeline, frame: FrameInput, image: Pending | bytes
    ) -> tuple[FrameStep, str, dict[str, float]]:
        """An image frame through `pipeline` with the features of `image` (see
        `features_of`): (its step, the observations its image gave as JSON text, the front
        end's timings ms)."""
        features, sig, timing = self.features_of(image)
        step = pipeline.step(frame, image=ImageFeatures(features, sig))
        return step, observations_json(step.observations), timing
