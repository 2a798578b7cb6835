"""A deterministic renderer: textured walls of the indoor world seen by a 360° camera.

The world is `indoor_sim`'s grid of rooms with doors. Every wall is a line
segment (doors are gaps) with two faces, each with its own texture: a smooth
grey background with flat posters (rectangles, some with a nested rectangle)
whose corners are recorded, so the true bearing and identity of a corner
feature can be checked. The camera stands `camera_height_m` above the floor;
walls are `wall_height_m` high; floor and ceiling are smooth gradients.

Ground truth per panorama column: the distance, the face and the wall point
(x, y) its ray hits first (`ColumnTruth`).

Convention: map frame x, y (m), yaw CCW from +x; a pose is (x, y, theta). A
column's bearing and a row's elevation follow `frontend.cameras.PanoramaCamera`;
an omni ring image follows `frontend.cameras.OmniCamera`. Face f = 2 k + side of
segment k (a -> b): side 0 faces the left of a -> b, side 1 the right. Texture
coordinate s runs from a to b in metres, z up from the floor.

Everything random comes from the `rng` passed in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from frontend.cameras import OmniCamera, PanoramaCamera
from graph.angles import wrap_angles
from service.offline.datasets.indoor_sim import IndoorWorld

__all__ = [
    "ColumnTruth",
    "TexturedWorld",
    "make_textured_world",
    "render_omni",
    "render_panorama",
    "visible_corners",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

_TEX_PX_PER_M = 100.0
_LEVELS = 4
_TILES_PER_ROW = 16


@dataclass(frozen=True)
class TexturedWorld:
    """Walls with textures, and the corners of their posters.

    Attributes:
        world: the rooms and doors (indoor_sim).
        seg_a, seg_b: (K, 2) wall segment end points, metres.
        atlas: mip levels of the texture atlas, level 0 at `_TEX_PX_PER_M` texels/m.
        tile_origin: (2K, 2) texel (column, row) of each face's tile in level 0.
        corners_xyz: (C, 3) poster corners: x, y on the wall, z above the floor (m).
        corner_face: (C,) face each corner is painted on.
        wall_height_m, camera_height_m: metres.
    """

    world: IndoorWorld
    seg_a: FloatArray
    seg_b: FloatArray
    atlas: tuple[NDArray[np.uint8], ...]
    tile_origin: FloatArray
    corners_xyz: FloatArray
    corner_face: IntArray
    wall_height_m: float
    camera_height_m: float


@dataclass(frozen=True)
class ColumnTruth:
    """What each ray sees first. Arrays of one shape (e.g. (W,) per panorama column).

    distance_m: inf where nothing is hit; face: -1 there; wall_xy: (..., 2).
    """

    distance_m: FloatArray
    face: IntArray
    along_m: FloatArray
    wall_xy: FloatArray


def _segments(world: IndoorWorld) -> tuple[FloatArray, FloatArray]:
    """Wall segments of the room grid; each door leaves a gap of door_width_m."""
    nx, ny = world.rooms
    size, half = world.room_size_m, 0.5 * world.door_width_m
    doors = {(round(float(x), 6), round(float(y), 6)) for x, y in world.doors}
    a: list[tuple[float, float]] = []
    b: list[tuple[float, float]] = []

    def add(p: tuple[float, float], q: tuple[float, float]) -> None:
        mid = (round(0.5 * (p[0] + q[0]), 6), round(0.5 * (p[1] + q[1]), 6))
        if mid in doors:
            ux, uy = (q[0] - p[0]) / size, (q[1] - p[1]) / size
            a.extend([p, (mid[0] + half * ux, mid[1] + half * uy)])
            b.extend([(mid[0] - half * ux, mid[1] - half * uy), q])
        else:
            a.append(p)
            b.append(q)

    for j in range(ny + 1):
        for i in range(nx):
            add((i * size, j * size), ((i + 1) * size, j * size))
    for i in range(nx + 1):
        for j in range(ny):
            add((i * size, j * size), (i * size, (j + 1) * size))
    return np.array(a, dtype=np.float64), np.array(b, dtype=np.float64)


def _smooth_noise(
    shape: tuple[int, int], cell_px: int, rng: np.random.Generator
) -> NDArray[np.float32]:
    """Smooth noise in [-1, 1]: a coarse random grid resized with cubic interpolation."""
    rows, cols = shape
    coarse = rng.uniform(-1.0, 1.0, (rows // cell_px + 2, cols // cell_px + 2)).astype(np.float32)
    big = cv2.resize(
        coarse,
        (coarse.shape[1] * cell_px, coarse.shape[0] * cell_px),
        interpolation=cv2.INTER_CUBIC,
    )
    return np.asarray(big[:rows, :cols], dtype=np.float32)


def _face_texture(
    length_m: float, height_m: float, tile: tuple[int, int], rng: np.random.Generator
) -> tuple[NDArray[np.uint8], list[tuple[float, float]]]:
    """One face's texture (tile-sized, the face's part at the left) and its corners (s, z)."""
    rows, cols = tile
    res = _TEX_PX_PER_M
    base = rng.uniform(90, 170)
    tex = base + 18.0 * _smooth_noise((rows, cols), 40, rng)
    corners: list[tuple[float, float]] = []
    placed: list[tuple[float, float, float, float]] = []
    for _ in range(int(6 * length_m)):
        w, h = rng.uniform(0.15, 0.7), rng.uniform(0.15, 0.7)
        if length_m - w - 0.2 <= 0.1:
            continue
        s0 = rng.uniform(0.1, length_m - w - 0.1)
        z0 = rng.uniform(0.25, height_m - h - 0.2)
        if any(
            s0 < q[2] + 0.08 and q[0] < s0 + w + 0.08 and z0 < q[3] + 0.08 and q[1] < z0 + h + 0.08
            for q in placed
        ):
            continue
        placed.append((s0, z0, s0 + w, z0 + h))
        level = base + rng.choice([-1.0, 1.0]) * rng.uniform(45, 85)
        rects = [(s0, z0, w, h, level)]
        if rng.random() < 0.4 and min(w, h) > 0.3:
            m = rng.uniform(0.06, 0.25 * min(w, h))
            inner = level + rng.choice([-1.0, 1.0]) * rng.uniform(45, 70)
            rects.append((s0 + m, z0 + m, w - 2 * m, h - 2 * m, inner))
        for rs, rz, rw, rh, value in rects:
            c0, c1 = round(rs * res), round((rs + rw) * res)
            r0, r1 = round((height_m - rz - rh) * res), round((height_m - rz) * res)
            patch = value + 12.0 * _smooth_noise((r1 - r0, c1 - c0), 8, rng)
            tex[r0:r1, c0:c1] = patch
            s_a, s_b = c0 / res, c1 / res
            z_a, z_b = height_m - r1 / res, height_m - r0 / res
            corners.extend([(s_a, z_a), (s_b, z_a), (s_a, z_b), (s_b, z_b)])
    blurred = cv2.GaussianBlur(tex.astype(np.float32), (0, 0), 0.6)
    return np.clip(blurred, 0, 255).astype(np.uint8), corners


def make_textured_world(
    world: IndoorWorld,
    *,
    rng: np.random.Generator,
    wall_height_m: float = 2.6,
    camera_height_m: float = 1.2,
) -> TexturedWorld:
    """Texture every face of every wall of `world` (deterministic given `rng`)."""
    seg_a, seg_b = _segments(world)
    lengths = np.linalg.norm(seg_b - seg_a, axis=1)
    tile = (round(wall_height_m * _TEX_PX_PER_M), math.ceil(lengths.max() * _TEX_PX_PER_M))
    faces = 2 * len(seg_a)
    tiles_down = math.ceil(faces / _TILES_PER_ROW)
    atlas = np.zeros((tiles_down * tile[0], _TILES_PER_ROW * tile[1]), dtype=np.uint8)
    origin = np.zeros((faces, 2))
    corners: list[tuple[float, float, float]] = []
    corner_face: list[int] = []
    for f in range(faces):
        k = f // 2
        r0, c0 = (f // _TILES_PER_ROW) * tile[0], (f % _TILES_PER_ROW) * tile[1]
        origin[f] = (c0, r0)
        tex, face_corners = _face_texture(float(lengths[k]), wall_height_m, tile, rng)
        atlas[r0 : r0 + tile[0], c0 : c0 + tile[1]] = tex
        unit = (seg_b[k] - seg_a[k]) / lengths[k]
        for s, z in face_corners:
            x, y = seg_a[k] + s * unit
            corners.append((float(x), float(y), z))
            corner_face.append(f)
    levels = [atlas]
    for _ in range(1, _LEVELS):
        levels.append(np.asarray(cv2.pyrDown(levels[-1]), dtype=np.uint8))
    return TexturedWorld(
        world=world,
        seg_a=seg_a,
        seg_b=seg_b,
        atlas=tuple(levels),
        tile_origin=origin,
        corners_xyz=np.array(corners, dtype=np.float64).reshape(-1, 3),
        corner_face=np.array(corner_face, dtype=np.int64),
        wall_height_m=wall_height_m,
        camera_height_m=camera_height_m,
    )


def raycast(tw: TexturedWorld, pose_xytheta: ArrayLike, bearings_rad: ArrayLike) -> ColumnTruth:
    """The first wall each ray (bearing from the pose, any shape) hits."""
    b = np.asarray(bearings_rad, dtype=np.float64)
    flat = b.reshape(-1)
    chunk = 32768
    if flat.size <= chunk:
        return _raycast(tw, pose_xytheta, b)
    parts = [_raycast(tw, pose_xytheta, flat[i : i + chunk]) for i in range(0, flat.size, chunk)]
    return ColumnTruth(
        distance_m=np.concatenate([p.distance_m for p in parts]).reshape(b.shape),
        face=np.concatenate([p.face for p in parts]).reshape(b.shape),
        along_m=np.concatenate([p.along_m for p in parts]).reshape(b.shape),
        wall_xy=np.concatenate([p.wall_xy for p in parts]).reshape(*b.shape, 2),
    )


def _raycast(tw: TexturedWorld, pose_xytheta: ArrayLike, b: FloatArray) -> ColumnTruth:
    x, y, theta = np.asarray(pose_xytheta, dtype=np.float64)
    shape = b.shape
    ang = (b + theta).reshape(-1, 1)
    dx, dy = np.cos(ang), np.sin(ang)
    ex, ey = (tw.seg_b - tw.seg_a).T
    ax, ay = tw.seg_a[:, 0] - x, tw.seg_a[:, 1] - y
    den = dx * ey - dy * ex  # (N, K)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (ax * ey - ay * ex) / den
        s = (ax * dy - ay * dx) / den
    ok = (np.abs(den) > 1e-12) & (t > 1e-9) & (s >= 0.0) & (s <= 1.0)
    t = np.where(ok, t, np.inf)
    k = np.argmin(t, axis=1)
    rows = np.arange(len(k))
    dist = t[rows, k]
    hit = np.isfinite(dist)
    side = ((ex[k] * (y - tw.seg_a[k, 1]) - ey[k] * (x - tw.seg_a[k, 0])) < 0).astype(np.int64)
    face = np.where(hit, 2 * k + side, -1)
    along = np.where(hit, s[rows, k] * np.hypot(ex[k], ey[k]), 0.0)
    wall = np.column_stack([x + dist * dx[:, 0], y + dist * dy[:, 0]])
    return ColumnTruth(
        distance_m=dist.reshape(shape),
        face=face.reshape(shape),
        along_m=along.reshape(shape),
        wall_xy=wall.reshape(*shape, 2),
    )


def _shade(
    tw: TexturedWorld,
    truth: ColumnTruth,
    elevation_rad: FloatArray,
    rad_per_px: float,
) -> NDArray[np.uint8]:
    """Intensities of rays (broadcast of truth's shape and elevation's shape), mip-mapped."""
    d = np.where(np.isfinite(truth.distance_m), truth.distance_m, 1e3)
    z = tw.camera_height_m + d * np.tan(elevation_rad)
    face = np.maximum(truth.face, 0)
    u0 = tw.tile_origin[face, 0] + truth.along_m * _TEX_PX_PER_M
    v0 = tw.tile_origin[face, 1] + (tw.wall_height_m - z) * _TEX_PX_PER_M
    u0, v0 = np.broadcast_arrays(u0, v0)
    texels_per_px = np.broadcast_to(d * rad_per_px * _TEX_PX_PER_M, u0.shape)
    level = np.clip(np.floor(np.log2(np.maximum(texels_per_px, 1.0))), 0, _LEVELS - 1)
    out = np.zeros(u0.shape, dtype=np.float32)
    for lv in range(_LEVELS):
        use = level == lv
        if not use.any():
            continue
        scale = 2.0**lv
        mx = ((u0 + 0.5) / scale - 0.5).astype(np.float32)
        my = ((v0 + 0.5) / scale - 0.5).astype(np.float32)
        sampled = cv2.remap(tw.atlas[lv], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out = np.where(use, sampled.astype(np.float32), out)
    e = np.broadcast_to(elevation_rad, u0.shape)
    floor = 55.0 + 25.0 * np.cos(e)
    ceiling = 215.0 - 20.0 * np.cos(e)
    # Antialiased wall edges: the share of the pixel's height (metres on the wall) that
    # lies above the floor / below the ceiling, so the edges do not staircase.
    pixel_m = np.maximum(d * rad_per_px / np.cos(e) ** 2, 1e-6)
    above_floor = np.clip(z / pixel_m + 0.5, 0.0, 1.0)
    below_ceiling = np.clip((tw.wall_height_m - z) / pixel_m + 0.5, 0.0, 1.0)
    wall = np.clip(above_floor + below_ceiling - 1.0, 0.0, 1.0)
    out = wall * out + (1.0 - above_floor) * floor + (1.0 - below_ceiling) * ceiling
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def render_panorama(
    tw: TexturedWorld, pose_xytheta: ArrayLike, camera: PanoramaCamera
) -> tuple[NDArray[np.uint8], ColumnTruth]:
    """A (height, width) grayscale panorama at the pose, and per-column ground truth (W,)."""
    bearings = camera.bearing_of_column(np.arange(camera.width))
    truth = raycast(tw, pose_xytheta, bearings)
    elevation = camera.elevation_of_row(np.arange(camera.height))[:, None]
    flat = ColumnTruth(
        truth.distance_m[None, :], truth.face[None, :], truth.along_m[None, :], truth.wall_xy
    )
    return _shade(tw, flat, elevation, camera.rad_per_px), truth


def render_omni(
    tw: TexturedWorld, pose_xytheta: ArrayLike, camera: OmniCamera
) -> NDArray[np.uint8]:
    """A (height, width) omni ring image at the pose, ray-traced pixel by pixel.

    Pixels outside the ring are black.
    """
    ys, xs = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    cx, cy = camera.centre_xy
    r = np.hypot(xs + 0.5 - cx, ys + 0.5 - cy)
    ring = (r >= camera.inner_radius_px) & (r <= camera.outer_radius_px)
    truth = raycast(tw, pose_xytheta, camera.bearing_of_pixel(xs, ys))
    elevations = camera.elevation_of_radius(r)
    # Angular footprint of a ring pixel along the circle (for mip selection).
    rad_per_px = 1.0 / max(float(np.median(r[ring])), 1.0)
    out = _shade(tw, truth, elevations, rad_per_px)
    out[~ring] = 0
    return out


def visible_corners(
    tw: TexturedWorld,
    pose_xytheta: ArrayLike,
    camera: PanoramaCamera,
    *,
    max_distance_m: float = 15.0,
    tolerance_m: float = 0.03,
) -> tuple[IntArray, FloatArray, FloatArray]:
    """Poster corners seen from the pose: (ids (V,), bearings (V,), elevations (V,)).

    A corner is visible when the ray towards it first hits its own face at its
    distance (within `tolerance_m`), it lies within the vertical field of view
    and `max_distance_m`.
    """
    x, y, theta = np.asarray(pose_xytheta, dtype=np.float64)
    rel = tw.corners_xyz[:, :2] - (x, y)
    dist = np.hypot(rel[:, 0], rel[:, 1])
    bearing = wrap_angles(np.arctan2(rel[:, 1], rel[:, 0]) - theta)
    elevation = np.arctan2(tw.corners_xyz[:, 2] - tw.camera_height_m, dist)
    cand = np.flatnonzero(
        (dist <= max_distance_m)
        & (np.abs(elevation) < 0.5 * camera.vfov_rad - camera.rad_per_px)
        & (dist > 0.1)
    )
    truth = raycast(tw, (x, y, theta), bearing[cand])
    ok = (truth.face == tw.corner_face[cand]) & (
        np.abs(truth.distance_m - dist[cand]) < tolerance_m
    )
    ids = cand[ok]
    return ids.astype(np.int64), bearing[ids], elevation[ids]
