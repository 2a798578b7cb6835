"""The coverage grid of a map: where the robots went, and how well each place is covered.

Convention: cells are squares of ``cell_m`` metres in the map frame; cell (ix, iy)
spans ``[origin_x + ix*cell_m, origin_x + (ix+1)*cell_m)`` in x and likewise in y;
rows of ``counts`` are indexed by iy (south to north), columns by ix (west to east).
A cell is *explored* when some pose of any robot lies in it. Its count is the
number of live landmarks whose mean observation position E(X) (Hochdorfer &
Schlegel eq. 1-2) lies within ``radius_m`` of the cell centre: how many landmarks
were observed from nearby. An explored cell with count 0 is a *hole*.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

MAX_CELLS_PER_SIDE = 200


def coverage_grid(
    positions_xy: NDArray[np.float64],
    observed_from_xy: NDArray[np.float64],
    *,
    cell_m: float,
    radius_m: float,
) -> dict[str, Any]:
    """The grid document: positions (N, 2) of poses, observed_from (M, 2) of live landmarks.

    The cell grows (doubling) if the explored area would need more than
    ``MAX_CELLS_PER_SIDE`` cells along a side.
    """
    positions = np.asarray(positions_xy, dtype=np.float64).reshape(-1, 2)
    observed = np.asarray(observed_from_xy, dtype=np.float64).reshape(-1, 2)
    if len(positions) == 0:
        return {
            "cell_m": cell_m,
            "radius_m": radius_m,
            "origin": {"x": 0.0, "y": 0.0},
            "width": 0,
            "height": 0,
            "counts": [],
            "explored_cells": 0,
            "holes": [],
        }
    lo = np.floor(positions.min(axis=0) / cell_m) * cell_m
    span = positions.max(axis=0) - lo
    while math.ceil(float(span.max()) / cell_m + 1e-9) > MAX_CELLS_PER_SIDE:
        cell_m *= 2.0
        lo = np.floor(positions.min(axis=0) / cell_m) * cell_m
        span = positions.max(axis=0) - lo
    width, height = (math.floor(float(s) / cell_m) + 1 for s in span)
    idx = np.floor((positions - lo) / cell_m).astype(np.int64)
    idx = np.clip(idx, 0, [width - 1, height - 1])
    explored = np.zeros((height, width), dtype=bool)
    explored[idx[:, 1], idx[:, 0]] = True

    cx = lo[0] + (np.arange(width) + 0.5) * cell_m
    cy = lo[1] + (np.arange(height) + 0.5) * cell_m
    gx, gy = np.meshgrid(cx, cy)  # (height, width)
    counts = np.zeros((height, width), dtype=np.int64)
    for ox, oy in observed:
        counts += (np.hypot(gx - ox, gy - oy) <= radius_m).astype(np.int64)

    rows: list[list[int | None]] = [
        [int(counts[iy, ix]) if explored[iy, ix] else None for ix in range(width)]
        for iy in range(height)
    ]
    holes = [
        {"ix": int(ix), "iy": int(iy), "x": float(cx[ix]), "y": float(cy[iy])}
        for iy, ix in zip(*np.nonzero(explored & (counts == 0)), strict=True)
    ]
    return {
        "cell_m": cell_m,
        "radius_m": radius_m,
        "origin": {"x": float(lo[0]), "y": float(lo[1])},
        "width": width,
        "height": height,
        "counts": rows,
        "explored_cells": int(explored.sum()),
        "holes": holes,
    }
