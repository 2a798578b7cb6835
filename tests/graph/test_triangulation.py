import math

import numpy as np
import pytest

from graph.triangulation import parallax, triangulate


def test_triangulate_exact_rays() -> None:
    target = np.array([2.0, 3.0])
    origins = np.array([[0.0, 0.0], [1.0, 0.0], [3.0, -0.5], [4.0, 1.0]])
    d = target - origins
    directions = np.arctan2(d[:, 1], d[:, 0])
    tri = triangulate(origins, directions, np.full(4, 0.01))
    assert tri is not None
    np.testing.assert_allclose(tri.point, target, atol=1e-9)
    np.testing.assert_allclose(tri.depths, np.hypot(d[:, 0], d[:, 1]), atol=1e-9)
    assert np.abs(tri.residuals).max() < 1e-6
    assert tri.parallax_rad == pytest.approx(parallax(directions))


def test_triangulate_parallel_rays_is_none() -> None:
    origins = np.array([[0.0, 0.0], [1.0, 0.0]])
    assert triangulate(origins, np.zeros(2), np.full(2, 0.01)) is None


def test_parallax_across_pi() -> None:
    assert parallax(np.array([math.pi - 0.05, -math.pi + 0.05])) == pytest.approx(0.1)


def test_point_behind_rays_has_negative_depth() -> None:
    origins = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    target = np.array([1.0, -3.0])
    d = target - origins
    directions = np.arctan2(d[:, 1], d[:, 0]) + math.pi  # pointing away
    tri = triangulate(origins, directions, np.full(3, 0.01))
    assert tri is None or np.any(tri.depths < 0)
