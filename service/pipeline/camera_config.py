"""The camera of a map's configuration (a map with one takes image frames), and what a
camera map created without some estimator fields gets (service.pipeline.config.MapConfig).

Units: pixels, degrees (as camera makers give them); every field says which.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


class StrictModel(BaseModel):
    """A part of a map's config: unknown fields (a typo) and NaN or infinities refused."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


MAX_CAMERA_PIXELS = 16 * 2**20
"""Largest image a camera may expect, pixels (the front end's decode limit)."""


class PanoramaCameraConfig(StrictModel):
    """An unwrapped 360° strip. Column u looks at bearing wrap(pi - 2 pi (u + 0.5) / width):
    the middle column looks forward, bearings grow towards the left (DESIGN.md, Cameras)."""

    model: Literal["panorama"] = Field("panorama", description="camera model")
    width: int = Field(2048, ge=8, description="image width, pixels (covers 360°)")
    height: int = Field(512, ge=1, description="image height, pixels")
    vfov_deg: float = Field(
        90.0, gt=0, lt=180, description="vertical field of view, degrees, centred on the horizon"
    )

    @model_validator(mode="after")
    def _bounded(self) -> PanoramaCameraConfig:
        if self.width * self.height > MAX_CAMERA_PIXELS:
            raise ValueError(f"width x height must be at most {MAX_CAMERA_PIXELS} pixels")
        return self


class OmniCameraConfig(StrictModel):
    """A raw catadioptric ring image, unwrapped to a panorama (frontend.cameras.OmniCamera)."""

    model: Literal["omni"] = Field(description="camera model")
    width: int = Field(ge=8, description="image width, pixels")
    height: int = Field(ge=8, description="image height, pixels")
    centre_xy: tuple[float, float] = Field(
        description="mirror centre in pixel coordinates (x right, y down), pixels"
    )
    inner_radius_px: float = Field(ge=0, description="radius seeing the bottom of the vfov, px")
    outer_radius_px: float = Field(gt=0, description="radius seeing the top of the vfov, px")
    forward_deg: float = Field(
        0.0, description="image angle (degrees, counter-clockwise from +x) looking forward"
    )
    mirrored: bool = Field(False, description="true if bearings grow clockwise in the image")
    pano_width: int = Field(2048, ge=8, description="width of the unwrapped panorama, pixels")
    pano_height: int = Field(512, ge=1, description="height of the unwrapped panorama, pixels")
    vfov_deg: float = Field(90.0, gt=0, lt=180, description="vertical field of view, degrees")

    @model_validator(mode="after")
    def _bounded(self) -> OmniCameraConfig:
        if not self.inner_radius_px < self.outer_radius_px:
            raise ValueError("need inner_radius_px < outer_radius_px")
        cx, cy = self.centre_xy
        if not (0 <= cx <= self.width and 0 <= cy <= self.height):
            raise ValueError("centre_xy must lie inside the image")
        for w, h in ((self.width, self.height), (self.pano_width, self.pano_height)):
            if w * h > MAX_CAMERA_PIXELS:
                raise ValueError(f"images must be at most {MAX_CAMERA_PIXELS} pixels")
        return self


CameraConfig = Annotated[PanoramaCameraConfig | OmniCameraConfig, Field(discriminator="model")]


CAMERA_LANDMARK_FACTORS = 60
"""Default `max_landmark_factors` of a camera map (see SlamConfig.max_landmark_factors)."""
CAMERA_GRAPH_FRAME_DISTANCE_M = 0.5
"""`graph_frame_distance_m` of a camera map created without one (see MapConfig.for_new_map)."""
CAMERA_ESTIMATOR_DEFAULTS = {
    "max_landmark_factors": CAMERA_LANDMARK_FACTORS,
    "graph_frame_distance_m": CAMERA_GRAPH_FRAME_DISTANCE_M,
}
"""What a camera map created without these estimator fields gets (MapConfig does it for
the service; an in-process replay of image frames applies them to its SlamConfig)."""
CAMERA_LANDMARK_CAP = 200
"""The service's default landmark cap of a camera map created without one (its setting
`default_camera_landmark_cap`). A camera map matches 45-60 landmarks a frame; at cap 50
the rendered runs' image ATE was 0.0242 / 0.0267 m (seeds 0 / 1), at 200 0.0083 / 0.0138."""
CAMERA_NOISE_DEFAULTS: dict[str, Any] = {"bearing_loss": "geman_mcclure", "huber_k": 1.0}
"""The `noise` fields a camera map created without them gets (MapConfig.for_new_map), and
an in-process replay of image frames (see SlamConfig.bearing_loss)."""
