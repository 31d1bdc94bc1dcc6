"""Voxelisation of normalised point clouds (docs/architecture.md §4, Sec. B.1).

Points already in [-1, 1)^3 (`nmjax.data.normalize`) are discretised on a G^3 grid with
cell = floor((p' + 1) / (2/G + 1e-5)), every hit cell having occupancy 1. The way back, from a
grid to the coordinates of its occupied cells, is `nmjax.metrics.voxel_points`.

All functions are vectorised NumPy (no Python loop over points or frames).
"""

from __future__ import annotations

import numpy as np

EPS = 1e-5  # the +1e-5 of the cell size, as in the released code


def voxel_indices(points: np.ndarray, grid: int) -> np.ndarray:
    """Integer cell of each normalised point: floor((p' + 1) / (2/G + 1e-5)), clipped to [0, G-1].

    Args:
      points: (..., 3) normalised points.
      grid: G.

    Returns:
      (..., 3) int64 cell indices in 'ij' order (axis 0 = x).
    """
    if grid < 1:
        raise ValueError(f"grid must be a positive number of cells, got {grid}")
    cell = np.floor((np.asarray(points, dtype=np.float64) + 1.0) / (2.0 / grid + EPS))
    return np.clip(cell, 0, grid - 1).astype(np.int64)


def voxelize(points: np.ndarray, grid: int) -> np.ndarray:
    """Occupancy grids of normalised point clouds.

    Args:
      points: (..., N, 3) points already normalised by `nmjax.data.normalize.normalize_sequence`.
      grid: G, the number of cells per axis.

    Returns:
      (..., G, G, G) float32, 1.0 at every cell hit by at least one point, 0.0 elsewhere.
    """
    points = np.asarray(points, dtype=np.float32)
    if points.ndim < 2 or points.shape[-1] != 3:
        raise ValueError(f"points must have shape (..., N, 3), got {points.shape}")
    lead = points.shape[:-2]
    n = points.shape[-2]
    cells = voxel_indices(points.reshape(-1, n, 3), grid)  # (F, N, 3)
    frames = cells.shape[0]
    flat = ((cells[..., 0] * grid + cells[..., 1]) * grid + cells[..., 2]).reshape(frames, n)
    flat = flat + (np.arange(frames, dtype=np.int64) * grid**3)[:, None]
    occupancy = np.zeros(frames * grid**3, dtype=np.float32)
    occupancy[flat.ravel()] = 1.0
    return occupancy.reshape(*lead, grid, grid, grid)
