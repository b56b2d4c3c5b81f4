"""The background node: world-frame Gaussians seeded from every frame's LiDAR (minus agent nodes) and camera rays."""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from omniscs.gaussians import GaussianParams, params_from_values

#: Neighbours averaged for a seed Gaussian's initial size (as 3DGS does with its point cloud).
SEED_NEIGHBOURS = 3

#: Floor on a seed Gaussian's initial size, metres (coincident LiDAR returns).
MIN_SEED_SCALE = 0.01


def neighbour_scales(points: np.ndarray,  # [N, 3]
                     max_scale: float) -> np.ndarray:  # -> [N] metres
    """Mean distance to the nearest ``SEED_NEIGHBOURS`` other points, clipped to [MIN_SEED_SCALE, max_scale]."""
    n = len(points)
    if n == 0:
        return np.zeros(0)
    if n == 1:
        return np.full(1, max_scale)
    k = min(SEED_NEIGHBOURS, n - 1)
    dist, _ = cKDTree(points).query(points, k=k + 1)
    return np.clip(dist[:, 1:].mean(axis=1), MIN_SEED_SCALE, max_scale)


def voxel_subsample(points: np.ndarray,  # [N, 3]
                    voxel: float, budget: int, rng: np.random.Generator) -> np.ndarray:  # -> [M] indices
    """One point per ``voxel``-sized cell (so the dense returns next to the car do not eat the budget),
    then a uniform draw down to ``budget``."""
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    cells = np.floor(points / voxel).astype(np.int64)
    cells -= cells.min(axis=0)
    extent = cells.max(axis=0) + 1
    if float(extent[0]) * float(extent[1]) * float(extent[2]) < 2.0 ** 62:
        # one int64 key per cell, in the rows' lexicographic order: a 1-D unique is much faster than one over rows
        _, first = np.unique((cells[:, 0] * extent[1] + cells[:, 1]) * extent[2] + cells[:, 2], return_index=True)
    else:
        _, first = np.unique(cells, axis=0, return_index=True)
    first = rng.permutation(first)
    return np.sort(first[:budget])


def init_background(points: np.ndarray,   # [N, 3] world
                    colours: np.ndarray,  # [N, 3] in [0, 1]
                    sh_degree: int, opacity: float, max_scale: float) -> GaussianParams:
    """World-frame Gaussians on ``points`` with view-independent colours, sized by point spacing."""
    scales = neighbour_scales(points, max_scale)
    n = len(points)
    return params_from_values(torch.from_numpy(points), torch.from_numpy(scales)[:, None].expand(n, 3),
                              torch.full((n,), opacity), torch.from_numpy(colours), sh_degree)
