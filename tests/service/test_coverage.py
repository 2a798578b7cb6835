"""The coverage grid: cell convention, counts of nearby observation means, holes."""

from __future__ import annotations

import numpy as np

from service.pipeline.coverage import MAX_CELLS_PER_SIDE, coverage_grid


def test_convention_cells_rows_are_y_columns_are_x() -> None:
    positions = np.array([[0.2, 0.3], [2.7, 0.4], [2.6, 1.5]])
    grid = coverage_grid(positions, np.zeros((0, 2)), cell_m=1.0, radius_m=0.5)
    assert grid["origin"] == {"x": 0.0, "y": 0.0}
    assert (grid["width"], grid["height"]) == (3, 2)
    explored = [[c is not None for c in row] for row in grid["counts"]]
    # row iy = 0 spans y in [0, 1): cells x in [0, 1) and [2, 3); row 1: x in [2, 3)
    assert explored == [[True, False, True], [False, False, True]]
    assert sorted((h["ix"], h["iy"]) for h in grid["holes"]) == [(0, 0), (2, 0), (2, 1)]
    assert grid["holes"][0]["x"] == 0.5 and grid["holes"][0]["y"] == 0.5


def test_counts_landmarks_observed_from_nearby_and_holes_are_the_rest() -> None:
    positions = np.array([[x, 0.5] for x in np.arange(0.5, 10, 0.5)])
    observed_from = np.array([[1.0, 0.5], [1.4, 0.6], [8.5, 0.5]])
    grid = coverage_grid(positions, observed_from, cell_m=1.0, radius_m=1.0)
    row = grid["counts"][0]
    assert row[0] == 2 and row[1] == 2 and row[8] == 1
    assert all(row[i] == 0 for i in range(3, 7))
    assert {h["ix"] for h in grid["holes"]} == {i for i, c in enumerate(row) if c == 0}


def test_a_large_area_coarsens_the_cells() -> None:
    positions = np.array([[0.0, 0.0], [1000.0, 10.0]])
    grid = coverage_grid(positions, np.zeros((0, 2)), cell_m=1.0, radius_m=2.0)
    assert grid["width"] <= MAX_CELLS_PER_SIDE and grid["cell_m"] > 1.0
    assert grid["explored_cells"] == 2


def test_no_poses_gives_an_empty_grid() -> None:
    grid = coverage_grid(np.zeros((0, 2)), np.zeros((0, 2)), cell_m=1.0, radius_m=2.0)
    assert grid["width"] == grid["height"] == 0 and grid["holes"] == []
