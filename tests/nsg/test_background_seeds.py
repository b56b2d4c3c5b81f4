"""Background seeding: one LiDAR point per voxel, then a uniform draw down to the budget."""
from __future__ import annotations

import numpy as np
import pytest

from omniscs.nsg.background import voxel_subsample


def rows_definition(points: np.ndarray, voxel: float, budget: int, rng: np.random.Generator) -> np.ndarray:
    """The rule as first written: the first point of every cell, cells in the rows' lexicographic order."""
    _, first = np.unique(np.floor(points / voxel).astype(np.int64), axis=0, return_index=True)
    return np.sort(rng.permutation(first)[:budget])


@pytest.mark.parametrize("n, budget", [(1, 5), (50, 5), (5_000, 100_000), (20_000, 700)])
def test_voxel_subsample_keeps_the_first_point_of_each_cell_and_draws_as_defined(n, budget):
    rng = np.random.default_rng(n)
    points = rng.uniform(-80.0, 120.0, (n, 3)) * [1.0, 1.0, 0.05]
    points = np.concatenate([points, points[: n // 2] + 1e-4])  # many cells hold several returns
    got = voxel_subsample(points, 0.5, budget, np.random.default_rng(7))
    assert np.array_equal(got, rows_definition(points, 0.5, budget, np.random.default_rng(7)))
    cells = np.floor(points[got] / 0.5).astype(np.int64)
    assert len(np.unique(cells, axis=0)) == len(got)  # never two points of one cell


def test_voxel_subsample_of_far_apart_cells_falls_back_to_rows():
    # cell indices spanning more than an int64 key can hold
    points = np.array([[-1e18, 0.0, 0.0], [1e18, 1e18, 1e18], [0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    got = voxel_subsample(points, 1.0, 10, np.random.default_rng(0))
    assert np.array_equal(got, rows_definition(points, 1.0, 10, np.random.default_rng(0)))
    assert voxel_subsample(np.zeros((0, 3)), 1.0, 10, np.random.default_rng(0)).size == 0
