"""The episodic normalisation box (docs/architecture.md §4, Sec. B.1): the one definition every
caller uses (training crops, evaluation crops, whole sequences, task clips, a retarget target mesh).

A cropped sequence is mapped into the cube [-1, 1)^3 with one bounding box shared by all of its
frames, p' = 2 (p - bmin) / (longest side + 1e-5) - 1: the minimum corner goes to -1 on every
axis and the far end of the longest side to just below 1; shorter sides are not centred. The
ground-truth joints go through the same map. Vectorised NumPy, float64 inside.
"""

from __future__ import annotations

import numpy as np

EPS = 1e-5  # the +1e-5 of the box's longest side, as in the released code


def normalization_box(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The bounding box of a sequence, as the map p' = scale (p - bmin) - 1.

    Args:
      points: (..., T, N, 3) points; each sequence of the leading axes gets its own box, spanning
        its T frames and N points.

    Returns:
      bmin (..., 1, 1, 3) and scale (..., 1, 1, 1) = 2 / (longest side + 1e-5), float64; both
      broadcast against (..., T, N, 3).
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim < 3 or points.shape[-1] != 3:
        raise ValueError(f"points must have shape (..., T, N, 3), got {points.shape}")
    if points.shape[-2] == 0 or points.shape[-3] == 0:
        raise ValueError(f"points has no frames or no points: shape {points.shape}")
    bmin = points.min(axis=(-3, -2), keepdims=True)
    bmax = points.max(axis=(-3, -2), keepdims=True)
    longest = (bmax - bmin).max(axis=-1, keepdims=True)
    return bmin, 2.0 / (longest + EPS)


def apply_box(x: np.ndarray, bmin: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3) float64: x' = scale (x - bmin) - 1 (`normalization_box`)."""
    return (np.asarray(x, np.float64) - bmin) * scale - 1.0


def undo_box(x: np.ndarray, bmin: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3) float64: the inverse of `apply_box`, back to the original units."""
    return (np.asarray(x, np.float64) + 1.0) / scale + bmin


def normalize_sequence(
    points: np.ndarray, joints: np.ndarray | None = None, *, box_frames: int | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Maps a sequence into [-1, 1)^3 with one bounding box over its frames.

    Args:
      points: (T, N, 3) points of one sequence, or (..., T, N, 3) for a batch of sequences, each
        normalised with its own box.
      joints: optional (..., T, J, 3) ground-truth joints; they follow the points' map and do not
        enter the bounding box.
      box_frames: the box spans only the first `box_frames` frames (default: all of them, a
        training crop). A longer clip then stays in the frame of its first crop; points that
        leave that box fall outside [-1, 1).

    Returns:
      (points', joints') as float32, joints' None when `joints` is None.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim < 3 or points.shape[-1] != 3:
        raise ValueError(f"points must have shape (..., T, N, 3), got {points.shape}")
    bmin, scale = normalization_box(points[..., :box_frames, :, :])
    out = apply_box(points, bmin, scale).astype(np.float32)
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
    return out, apply_box(joints, bmin, scale).astype(np.float32)
