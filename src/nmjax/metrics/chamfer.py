"""Chamfer distances between point sets, and the two voxel metrics built on them: 4D tracking
(Table 2) and the motion Chamfer distance M-CD (Eq. 22).

`chamfer_distance` is pure and jit-able; the front-ends (`tracking_chamfer`, `motion_chamfer`)
turn voxel grids into point sets with NumPy (`voxel_points`: their sizes vary per frame) and pad
them to a few bucket sizes (`point_chamfer`) so that the compiled kernel is reused.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

MAX_SQ_DIST = 12.0  # squared diagonal of the normalised cube [-1, 1]^3: the worst possible CD term
TRACKING_SCALE = 1e4  # Table 2 reports the Chamfer distance x 1e4


def voxel_points(voxels: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """Coordinates of the occupied cells of one grid on the `linspace(-1, 1, G)` grid: the point
    set V_t that the Chamfer metrics compare (docs/architecture.md §4's coordinate grid).

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


def _nearest_sq_dist(a: Array, b: Array, b_mask: Array, chunk: int) -> Array:
    """(N,) squared distance from each row of a (N, 3) to the nearest valid row of b (M, 3)."""
    n = a.shape[0]
    chunk = max(1, min(chunk, n))
    pad = (-n) % chunk
    blocks = jnp.pad(a, ((0, pad), (0, 0))).reshape(-1, chunk, 3)
    b_sq = jnp.sum(jnp.square(b), axis=-1)

    def block(x):  # (chunk, 3) -> (chunk,); a (chunk, M) matrix at a time, never (chunk, M, 3)
        cross = jnp.matmul(x, b.T, precision=jax.lax.Precision.HIGHEST)
        d = jnp.sum(jnp.square(x), axis=-1)[:, None] - 2.0 * cross + b_sq[None, :]
        return jnp.maximum(jnp.min(jnp.where(b_mask[None, :], d, jnp.inf), axis=-1), 0.0)

    return jax.lax.map(block, blocks).reshape(-1)[:n]


def chamfer_distance(
    a: Array,
    b: Array,
    a_mask: Array | None = None,
    b_mask: Array | None = None,
    *,
    empty_value: float = float("nan"),
    chunk: int = 2048,
) -> Array:
    """Symmetric Chamfer distance (Fan et al. 2017) between two point sets, squared distances:

    CD(A, B) = mean_{a in A} min_{b in B} ||a - b||^2 + mean_{b in B} min_{a in A} ||a - b||^2.

    Args:
        a: (N, 3) points; b: (M, 3) points.
        a_mask, b_mask: optional (N,), (M,) booleans marking the valid (non-padding) points.
        empty_value: result when exactly one set is empty (both empty gives 0).
        chunk: rows of `a` (and of `b`) compared at once; bounds memory to chunk x M floats.

    Returns:
        scalar.
    """
    a_mask = jnp.ones(a.shape[0], bool) if a_mask is None else a_mask
    b_mask = jnp.ones(b.shape[0], bool) if b_mask is None else b_mask
    na, nb = jnp.sum(a_mask), jnp.sum(b_mask)
    if a.shape[0] == 0 or b.shape[0] == 0:  # static: nothing to compare
        return jnp.asarray(0.0 if a.shape[0] == b.shape[0] else empty_value, jnp.float32)
    da = _nearest_sq_dist(a, b, b_mask, chunk)
    db = _nearest_sq_dist(b, a, a_mask, chunk)
    ab = jnp.sum(jnp.where(a_mask, da, 0.0)) / jnp.maximum(na, 1)
    ba = jnp.sum(jnp.where(b_mask, db, 0.0)) / jnp.maximum(nb, 1)
    both, neither = (na > 0) & (nb > 0), (na == 0) & (nb == 0)
    return jnp.where(both, ab + ba, jnp.where(neither, 0.0, empty_value))


@functools.partial(jax.jit, static_argnames=("empty_value",))
def _chamfer_padded(a, b, a_mask, b_mask, empty_value):
    return chamfer_distance(a, b, a_mask, b_mask, empty_value=empty_value)


def _padded(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pads (M, 3) to the next power of two (>= 64) rows with a validity mask."""
    size = max(64, 1 << int(np.ceil(np.log2(max(len(points), 1)))))
    out = np.zeros((size, 3), np.float32)
    out[: len(points)] = points
    return out, np.arange(size) < len(points)


def point_chamfer(a: np.ndarray, b: np.ndarray, empty_value: float = float("nan")) -> float:
    """`chamfer_distance` of two NumPy point sets of any size, padded to reuse compilations."""
    (pa, ma), (pb, mb) = _padded(np.asarray(a)), _padded(np.asarray(b))
    return float(_chamfer_padded(pa, pb, ma, mb, empty_value))


def _check_sequences(v: np.ndarray, v_hat: np.ndarray, name: str) -> None:
    if v.shape != v_hat.shape or v.ndim != 4:
        raise ValueError(
            f"{name}: expected two (T, G, G, G) voxel sequences of equal shape, "
            f"got {v.shape} and {v_hat.shape}"
        )


def tracking_chamfer(
    voxels: np.ndarray, recon: np.ndarray, threshold: float = 0.5, scale: float = TRACKING_SCALE
) -> float:
    """4D-tracking Chamfer distance of Table 2 (x1e4): mean over frames of CD(V_t, V-hat_t).

    V_t are the occupied cells of the ground truth, V-hat_t those of the reconstruction
    thresholded at `threshold` (cell coordinates on the linspace(-1, 1, G) grid). A frame whose
    reconstruction is empty while the ground truth is not scores the worst possible value
    (MAX_SQ_DIST = 12, the squared diagonal of the cube) instead of being skipped.

    Args:
        voxels: (T, G, G, G) ground-truth occupancy.
        recon: (T, G, G, G) reconstructed probabilities (or occupancy).
        threshold: occupancy threshold for both grids.
        scale: multiplier of the reported value (Table 2 uses 1e4).

    Returns:
        scaled mean Chamfer distance over the T frames.
    """
    voxels, recon = np.asarray(voxels), np.asarray(recon)
    _check_sequences(voxels, recon, "tracking_chamfer")
    per_frame = [
        point_chamfer(voxel_points(v, threshold), voxel_points(r, threshold), MAX_SQ_DIST)
        for v, r in zip(voxels, recon, strict=True)
    ]
    return float(np.mean(per_frame)) * scale


def motion_chamfer(voxels: np.ndarray, recon: np.ndarray, threshold: float = 0.5) -> float:
    """Motion Chamfer Distance, Eq. 22: Chamfer distances of the frame-to-frame differences.

    M-CD = 1/(T-1) sum_{t=2..T} CD(V+_t, V-hat+_t) + CD(V-_t, V-hat-_t), where V+_t (V-_t) are the
    cells that become occupied (empty) between frames t-1 and t, after thresholding both
    sequences at `threshold`. Both sets empty (no motion on either side) counts 0; exactly one
    empty counts MAX_SQ_DIST = 12 (the worst possible value), so missing motion is penalised.
    Unscaled.

    Args:
        voxels: (T, G, G, G) ground-truth sequence, T >= 2.
        recon: (T, G, G, G) generated / interpolated sequence.
        threshold: occupancy threshold.

    Returns:
        M-CD (a float).
    """
    voxels, recon = np.asarray(voxels), np.asarray(recon)
    _check_sequences(voxels, recon, "motion_chamfer")
    if voxels.shape[0] < 2:
        raise ValueError(f"motion_chamfer needs at least 2 frames, got {voxels.shape[0]}")
    occ, occ_hat = voxels >= threshold, recon >= threshold
    total = 0.0
    for t in range(1, occ.shape[0]):  # NumPy front-end: point sets differ in size per frame
        for sign in (1, -1):
            gained = occ[t] & ~occ[t - 1] if sign > 0 else occ[t - 1] & ~occ[t]
            gained_hat = occ_hat[t] & ~occ_hat[t - 1] if sign > 0 else occ_hat[t - 1] & ~occ_hat[t]
            total += point_chamfer(
                voxel_points(gained.astype(np.float32)),
                voxel_points(gained_hat.astype(np.float32)),
                MAX_SQ_DIST,
            )
    return total / (occ.shape[0] - 1)
