"""Episodic normalisation and voxelisation of point-cloud sequences (DESIGN section 4, Sec. B.1).

A cropped sequence is mapped into the cube [-1, 1)^3 with one bounding box shared by all of its
frames, p' = 2 (p - bmin) / (longest side + 1e-5) - 1, without centring the shorter sides; the
ground-truth joints go through the same map. Each frame is then discretised on a G^3 grid with
cell = floor((p' + 1) / (2/G + 1e-5)), every hit cell having occupancy 1. `voxel_points` goes back
from a grid to the coordinates of its occupied cells on the `linspace(-1, 1, G)` grid, the point
set V_t of the volume-fitting loss (Eq. 8) and of the Chamfer metrics.

All functions are vectorised NumPy (no Python loop over points or frames).
"""

from __future__ import annotations

import numpy as np

EPS = 1e-5  # the +1e-5 of both maps, as in the released code


def normalize_sequence(
    points: np.ndarray, joints: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Maps a sequence into [-1, 1)^3 with one bounding box over all of its frames.

    p' = 2 (p - bmin) / (max(bmax - bmin) + 1e-5) - 1, so the minimum corner goes to -1 on every
    axis and the far end of the longest side to just below 1; shorter sides are not centred.

    Args:
      points: (T, N, 3) points of one sequence, or (..., T, N, 3) for a batch of sequences, each
        normalised with its own box (the box spans its T frames and N points).
      joints: optional (..., T, J, 3) ground-truth joints; they follow the points' map and do not
        enter the bounding box.

    Returns:
      (points', joints') as float32, joints' None when `joints` is None.
    """
    points = np.asarray(points, dtype=np.float64)  # float64 inside, float32 out
    if points.ndim < 3 or points.shape[-1] != 3:
        raise ValueError(f"points must have shape (..., T, N, 3), got {points.shape}")
    if points.shape[-2] == 0 or points.shape[-3] == 0:
        raise ValueError(f"points has no frames or no points: shape {points.shape}")
    bmin = points.min(axis=(-3, -2), keepdims=True)  # (..., 1, 1, 3)
    bmax = points.max(axis=(-3, -2), keepdims=True)
    longest = (bmax - bmin).max(axis=-1, keepdims=True)  # (..., 1, 1, 1)
    scale = 2.0 / (longest + EPS)
    out = ((points - bmin) * scale - 1.0).astype(np.float32)
    if joints is None:
        return out, None
    joints = np.asarray(joints, dtype=np.float64)
    if joints.ndim != points.ndim or joints.shape[-1] != 3:
        raise ValueError(
            f"joints must have shape (..., T, J, 3) matching points {points.shape}, "
            f"got {joints.shape}"
        )
    if joints.shape[:-2] != points.shape[:-2]:
        raise ValueError(
            f"joints {joints.shape} and points {points.shape} differ in their leading (..., T) axes"
        )
    return out, ((joints - bmin) * scale - 1.0).astype(np.float32)


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
      points: (..., N, 3) points already normalised by `normalize_sequence`.
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


def voxel_points(voxels: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """Coordinates of the occupied cells of one grid on the `linspace(-1, 1, G)` grid.

    Args:
      voxels: (G, G, G) occupancy (binary or probabilities).
      threshold: a cell is occupied when its value is >= threshold (0.5 also thresholds a
        reconstruction, as the 4D-tracking metric does).

    Returns:
      (M, 3) float32 coordinates in 'ij' order, M the number of occupied cells (may be 0).
    """
    voxels = np.asarray(voxels)
    if voxels.ndim != 3 or len(set(voxels.shape)) != 1:
        raise ValueError(f"voxels must be one cubic grid (G, G, G), got {voxels.shape}")
    axis = np.linspace(-1.0, 1.0, voxels.shape[0], dtype=np.float32)
    return axis[np.argwhere(voxels >= threshold)]
