"""Planar triangulation of bearing rays (GTSAM has none for 2-D).

A ray i starts at origins[i] (map frame, metres) with world direction
directions_rad[i] = robot heading + bearing, wrapped. Least-squares
intersection (one row n_i . p = n_i . c_i per ray, n_i normal to the ray)
followed by Gauss-Newton on the bearing residuals.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graph.angles import wrap_angles


@dataclass(frozen=True, slots=True)
class Triangulation:
    point: NDArray[np.float64]
    """(2,) landmark position, metres, map frame."""
    covariance: NDArray[np.float64]
    """(2, 2) position covariance from the bearing noise alone, m^2."""
    depths: NDArray[np.float64]
    """(N,) signed distance along each ray to the point, metres."""
    residuals: NDArray[np.float64]
    """(N,) bearing residual of each ray in sigmas."""
    parallax_rad: float
    """Largest angle between two rays' directions, radians in [0, pi]."""


def _ill_conditioned(m: NDArray[np.float64], limit: float = 1e10) -> bool:
    """True when a symmetric (2, 2) matrix's condition number exceeds `limit`."""
    half_trace = 0.5 * (m[0, 0] + m[1, 1])
    root = np.hypot(0.5 * (m[0, 0] - m[1, 1]), m[0, 1])
    smallest = half_trace - root
    return bool(smallest <= 0 or (half_trace + root) > limit * smallest)


def parallax(directions_rad: NDArray[np.float64]) -> float:
    """Largest pairwise angle between ray directions (N,), radians."""
    d = np.asarray(directions_rad, dtype=np.float64)
    diffs = np.abs(wrap_angles(d[:, None] - d[None, :]))
    return float(diffs.max()) if d.size else 0.0


def triangulate(
    origins: NDArray[np.float64],
    directions_rad: NDArray[np.float64],
    sigmas_rad: NDArray[np.float64],
    *,
    iterations: int = 5,
) -> Triangulation | None:
    """Intersect N >= 2 rays: origins (N, 2), directions (N,), sigmas (N,).

    Returns None when the rays are (numerically) parallel.
    """
    c = np.asarray(origins, dtype=np.float64)
    phi = np.asarray(directions_rad, dtype=np.float64)
    s = np.asarray(sigmas_rad, dtype=np.float64)
    normals = np.stack([-np.sin(phi), np.cos(phi)], axis=1)
    a = normals / s[:, None]
    b = np.einsum("ij,ij->i", normals, c) / s
    ata = a.T @ a
    if _ill_conditioned(ata):
        return None
    p = np.linalg.solve(ata, a.T @ b)
    cov = np.asarray(np.linalg.inv(ata), dtype=np.float64)
    for _ in range(iterations):
        delta = p[None, :] - c
        r2 = np.einsum("ij,ij->i", delta, delta)
        if np.any(r2 < 1e-12):
            return None
        predicted = np.arctan2(delta[:, 1], delta[:, 0])
        res = wrap_angles(predicted - phi) / s
        jac = np.stack([-delta[:, 1], delta[:, 0]], axis=1) / (r2 * s)[:, None]
        jtj = jac.T @ jac
        if _ill_conditioned(jtj):
            return None
        step = np.linalg.solve(jtj, -jac.T @ res)
        p = p + step
        cov = np.asarray(np.linalg.inv(jtj), dtype=np.float64)
        if float(np.abs(step).max()) < 1e-9:
            break
    delta = p[None, :] - c
    depths: NDArray[np.float64] = delta[:, 0] * np.cos(phi) + delta[:, 1] * np.sin(phi)
    residuals = wrap_angles(np.arctan2(delta[:, 1], delta[:, 0]) - phi) / s
    return Triangulation(p, cov, depths, residuals, parallax(phi))
