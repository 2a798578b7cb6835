"""Camera models: which direction each pixel looks, and the omni ring's unwrapping.

Every image the front end works on is a `PanoramaCamera` image; an `OmniCamera`
image is unwrapped to one first (`OmniCamera.unwrap`, OpenCV remap with maps
computed once per camera).

Bearings are radians in the robot frame, counter-clockwise from the robot's
forward axis (+x), wrapped to (-pi, pi] (graph.angles). Elevations are radians
above the horizontal plane of the camera (positive up).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from graph.angles import TWO_PI, wrap_angles

FloatArray = NDArray[np.float64]

__all__ = ["CameraModel", "OmniCamera", "PanoramaCamera", "camera_from_config"]


@dataclass(frozen=True)
class PanoramaCamera:
    """An unwrapped 360° strip (equirectangular / cylindrical) of `width` x `height` pixels.

    Convention:
        Pixel (u, v) is column u (0-based, left to right) and row v (0-based, top
        to bottom); its centre is at (u + 0.5, v + 0.5). The centre of column u
        looks at bearing ``wrap(pi - 2 pi (u + 0.5) / width)``: the middle of the
        image looks forward (bearing 0), the left edge looks backwards, bearings
        grow towards the left of the image (counter-clockwise, REP-103), and the
        image wraps around between its last and first columns. Subpixel columns
        (a float u) follow the same formula.
        Rows are linear in elevation over `vfov_rad`, centred on the horizon: the
        centre of row v looks at elevation ``vfov (0.5 - (v + 0.5) / height)``
        (top row up, bottom row down).
    """

    width: int = 2048
    height: int = 512
    vfov_rad: float = math.radians(90.0)

    def __post_init__(self) -> None:
        if self.width < 8 or self.height < 1:
            raise ValueError(
                f"panorama must be at least 8x1 pixels, got {self.width}x{self.height}"
            )
        if not 0.0 < self.vfov_rad < math.pi:
            raise ValueError("vfov_rad must lie in (0, pi)")

    @property
    def kind(self) -> str:
        return "panorama"

    @property
    def rad_per_px(self) -> float:
        """Horizontal angular resolution: radians per column."""
        return TWO_PI / self.width

    @property
    def image_shape(self) -> tuple[int, int]:
        """(rows, columns) of the images this camera accepts."""
        return (self.height, self.width)

    def bearing_of_column(self, u: ArrayLike) -> FloatArray:
        """Bearings (rad) of (any shape) column coordinates u (pixel index, may be fractional)."""
        u = np.asarray(u, dtype=np.float64)
        return wrap_angles(math.pi - TWO_PI * (u + 0.5) / self.width)

    def column_of_bearing(self, bearing_rad: ArrayLike) -> FloatArray:
        """Columns u in [-0.5, width - 0.5) whose centre formula gives these bearings."""
        b = np.asarray(bearing_rad, dtype=np.float64)
        u = (math.pi - b) * self.width / TWO_PI - 0.5
        return np.mod(u + 0.5, self.width) - 0.5

    def elevation_of_row(self, v: ArrayLike) -> FloatArray:
        """Elevations (rad, up positive) of row coordinates v (may be fractional)."""
        v = np.asarray(v, dtype=np.float64)
        return self.vfov_rad * (0.5 - (v + 0.5) / self.height)

    def row_of_elevation(self, elevation_rad: ArrayLike) -> FloatArray:
        """Row coordinates of elevations; the inverse of `elevation_of_row`."""
        e = np.asarray(elevation_rad, dtype=np.float64)
        return (0.5 - e / self.vfov_rad) * self.height - 0.5

    def as_config(self) -> dict[str, Any]:
        return {
            "model": "panorama",
            "width": self.width,
            "height": self.height,
            "vfov_deg": math.degrees(self.vfov_rad),
        }


@dataclass(frozen=True)
class OmniCamera:
    """A raw catadioptric image: the ring between two radii around the mirror's centre.

    Convention:
        Image pixel (x, y) is column x, row y (0-based, y down), centre at
        (x + 0.5, y + 0.5) as in `PanoramaCamera`. `centre_xy` is the mirror's
        centre in these pixel coordinates. The image angle of a point is
        ``atan2(-(y - cy), x - cx)``: 0 to the right of the centre, +pi/2 straight
        up in the picture (counter-clockwise as the picture is viewed).
        `forward_rad` is the image angle that looks along the robot's forward
        axis. Not mirrored: bearing = wrap(image angle - forward_rad) (bearings
        grow counter-clockwise in the picture); mirrored: bearing =
        wrap(forward_rad - image angle).
        Radius is linear in elevation: `outer_radius_px` sees the top of the
        vertical field of view and `inner_radius_px` the bottom, so the unwrapped
        panorama's row 0 comes from the outer circle.
        `unwrap` gives the `panorama` camera's image (`pano_width` x `pano_height`,
        same vertical field of view), to which every PanoramaCamera convention
        applies.
    """

    width: int
    height: int
    centre_xy: tuple[float, float]
    inner_radius_px: float
    outer_radius_px: float
    forward_rad: float = 0.0
    mirrored: bool = False
    pano_width: int = 2048
    pano_height: int = 512
    vfov_rad: float = math.radians(90.0)
    _maps: tuple[NDArray[np.float32], NDArray[np.float32]] | None = field(
        default=None, init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        if self.width < 8 or self.height < 8:
            raise ValueError("omni image must be at least 8x8 pixels")
        if not 0.0 <= self.inner_radius_px < self.outer_radius_px:
            raise ValueError("need 0 <= inner_radius_px < outer_radius_px")
        cx, cy = self.centre_xy
        if not (0 <= cx <= self.width and 0 <= cy <= self.height):
            raise ValueError("centre_xy must lie inside the image")
        # Validate the panorama parameters by building it.
        PanoramaCamera(self.pano_width, self.pano_height, self.vfov_rad)

    @property
    def kind(self) -> str:
        return "omni"

    @property
    def image_shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    @property
    def panorama(self) -> PanoramaCamera:
        """The camera of the unwrapped images."""
        return PanoramaCamera(self.pano_width, self.pano_height, self.vfov_rad)

    @property
    def rad_per_px(self) -> float:
        return self.panorama.rad_per_px

    def image_angle_of_bearing(self, bearing_rad: ArrayLike) -> FloatArray:
        b = np.asarray(bearing_rad, dtype=np.float64)
        return self.forward_rad - b if self.mirrored else self.forward_rad + b

    def bearing_of_pixel(self, x: ArrayLike, y: ArrayLike) -> FloatArray:
        """Bearings of image pixel coordinates (x, y) (any matching shapes)."""
        cx, cy = self.centre_xy
        phi = np.arctan2(-(np.asarray(y, np.float64) + 0.5 - cy), np.asarray(x) + 0.5 - cx)
        return wrap_angles(self.forward_rad - phi if self.mirrored else phi - self.forward_rad)

    def radius_of_elevation(self, elevation_rad: ArrayLike) -> FloatArray:
        e = np.asarray(elevation_rad, dtype=np.float64)
        t = 0.5 - e / self.vfov_rad  # 0 at the top of the field of view, 1 at the bottom
        return self.outer_radius_px + t * (self.inner_radius_px - self.outer_radius_px)

    def elevation_of_radius(self, radius_px: ArrayLike) -> FloatArray:
        r = np.asarray(radius_px, dtype=np.float64)
        t = (r - self.outer_radius_px) / (self.inner_radius_px - self.outer_radius_px)
        return self.vfov_rad * (0.5 - t)

    def pixel_of_direction(
        self, bearing_rad: ArrayLike, elevation_rad: ArrayLike
    ) -> tuple[FloatArray, FloatArray]:
        """Image pixel coordinates (x, y) that look at these directions."""
        phi = self.image_angle_of_bearing(bearing_rad)
        r = self.radius_of_elevation(elevation_rad)
        cx, cy = self.centre_xy
        return cx + r * np.cos(phi) - 0.5, cy - r * np.sin(phi) - 0.5

    def unwrap_maps(self) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """(pano_height, pano_width) float32 maps for cv2.remap, computed once."""
        if self._maps is None:
            pano = self.panorama
            u = np.arange(pano.width, dtype=np.float64)
            v = np.arange(pano.height, dtype=np.float64)
            b = pano.bearing_of_column(u)[None, :]
            e = pano.elevation_of_row(v)[:, None]
            x, y = self.pixel_of_direction(b, e)
            maps = (x.astype(np.float32), y.astype(np.float32))
            object.__setattr__(self, "_maps", maps)
            return maps
        return self._maps

    def unwrap(self, image: NDArray[np.uint8]) -> NDArray[np.uint8]:
        """The panorama of a ring image (bilinear; outside the image is black)."""
        mx, my = self.unwrap_maps()
        out = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        return np.asarray(out, dtype=np.uint8)

    def as_config(self) -> dict[str, Any]:
        return {
            "model": "omni",
            "width": self.width,
            "height": self.height,
            "centre_xy": list(self.centre_xy),
            "inner_radius_px": self.inner_radius_px,
            "outer_radius_px": self.outer_radius_px,
            "forward_deg": math.degrees(self.forward_rad),
            "mirrored": self.mirrored,
            "pano_width": self.pano_width,
            "pano_height": self.pano_height,
            "vfov_deg": math.degrees(self.vfov_rad),
        }


CameraModel = PanoramaCamera | OmniCamera


def camera_from_config(config: dict[str, Any]) -> CameraModel:
    """Build a camera from its config object (as `as_config` writes it; angles in degrees).

    Raises ValueError on an unknown model or bad parameters.
    """
    model = config.get("model", "panorama")
    vfov = math.radians(float(config.get("vfov_deg", 90.0)))
    if model == "panorama":
        return PanoramaCamera(int(config.get("width", 2048)), int(config.get("height", 512)), vfov)
    if model == "omni":
        cx, cy = config["centre_xy"]
        return OmniCamera(
            width=int(config["width"]),
            height=int(config["height"]),
            centre_xy=(float(cx), float(cy)),
            inner_radius_px=float(config["inner_radius_px"]),
            outer_radius_px=float(config["outer_radius_px"]),
            forward_rad=math.radians(float(config.get("forward_deg", 0.0))),
            mirrored=bool(config.get("mirrored", False)),
            pano_width=int(config.get("pano_width", 2048)),
            pano_height=int(config.get("pano_height", 512)),
            vfov_rad=vfov,
        )
    raise ValueError(f"unknown camera model {model!r} (expected 'panorama' or 'omni')")
