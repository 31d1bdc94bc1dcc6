"""Keypoint maps: coordinate grids, heatmaps -> keypoints, keypoints -> gaussian maps
(docs/architecture.md §6), and the affinity between keypoints: from its free parameters (Eq. 12),
combined over N (influence).

Conventions (docs/architecture.md §4): the coordinate of an n-cell axis is `linspace(-1, 1, n)`,
axes in 'ij' order (grid axis 0 is x); keypoints are `(..., K, 4)` with xyz in the normalised cube
and the intensity alpha last. Everything here is pure and works under `jit`, `vmap` and `grad`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array

_EPS = 1e-6


def axis_coords(n: int) -> Array:
    """Coordinates of the n cells of one grid axis, `linspace(-1, 1, n)`. Shape (n,)."""
    return jnp.linspace(-1.0, 1.0, n, dtype=jnp.float32)


def coord_grid(n: int) -> Array:
    """Coordinates of every cell of an n^3 grid.

    Args:
        n: cells per axis.

    Returns:
        (n, n, n, 3) float32; `grid[i, j, l] = (x_i, y_j, z_l)` with x = y = z = linspace(-1, 1, n).
    """
    x = axis_coords(n)
    return jnp.stack(jnp.meshgrid(x, x, x, indexing="ij"), axis=-1)


def add_coord_channels(x: Array) -> Array:
    """CoordConv input: appends the three coordinate channels of the grid (docs/architecture.md §6).

    Args:
        x: (..., n, n, n, C) channels-last feature volume.

    Returns:
        (..., n, n, n, C + 3), the last three channels being `coord_grid(n)` broadcast over the
        leading axes.
    """
    n = x.shape[-2]
    if x.ndim < 4 or x.shape[-4] != n or x.shape[-3] != n:
        raise ValueError(f"add_coord_channels: expected (..., n, n, n, C) input, got {x.shape}")
    grid = jnp.broadcast_to(coord_grid(n).astype(x.dtype), (*x.shape[:-1], 3))
    return jnp.concatenate([x, grid], axis=-1)


def heatmap_to_keypoints(heatmaps: Array, temperature: float = 1.0) -> Array:
    """Keypoints from non-negative heatmaps (paper Eq. 6 -> x = (mu, alpha), docs/architecture.md
    §6).

    alpha_k = mean of heatmap k over the grid, divided by (max over K of those means + 1e-6).
    mu_k along axis d = expectation of `linspace(-1, 1, g)` under the marginal of heatmap k on that
    axis (sum over the two other axes) of the heatmap with 1e-6 added to every cell, normalised
    to sum 1: the release's convention, under which a heatmap that is near zero everywhere puts
    its keypoint near the grid centre (a heatmap of zeros: exactly at it).

    Args:
        heatmaps: (..., g, g, g, K) non-negative (softplus) heatmaps.
        temperature: mu is taken under heatmap^(1 / temperature) (alpha is not): 1 is the
            paper; below 1 sharpens the heatmap around its peak and thins the softplus floor
            (for softplus in its exponential regime, h = e^z, it is a spatial softmax of z at
            that temperature). Static.

    Returns:
        (..., K, 4) keypoints: xyz then alpha in [0, 1].
    """
    if heatmaps.ndim < 4:
        raise ValueError(f"heatmap_to_keypoints: expected (..., g, g, g, K), got {heatmaps.shape}")
    if not temperature > 0:
        raise ValueError(f"heatmap_to_keypoints: temperature must be > 0, got {temperature}")
    g = heatmaps.shape[-2]
    mean = jnp.mean(heatmaps, axis=(-4, -3, -2))  # (..., K)
    alpha = mean / (jnp.max(mean, axis=-1, keepdims=True) + _EPS)
    if temperature != 1.0:
        # Scaled by the peak first, so that a large power neither overflows nor underflows.
        peak = jnp.max(heatmaps, axis=(-4, -3, -2), keepdims=True)
        heatmaps = (heatmaps / (peak + _EPS)) ** (1.0 / temperature)
    coords = axis_coords(g)
    mus = []
    for axis in (-4, -3, -2):  # x, y, z: three fixed axes, not a loop over data
        others = tuple(a for a in (-4, -3, -2) if a != axis)
        # 1e-6 in each of the g^2 cells summed into a marginal cell.
        marginal = jnp.sum(heatmaps, axis=others) + _EPS * g * g  # (..., g, K)
        prob = marginal / jnp.sum(marginal, axis=-2, keepdims=True)
        mus.append(jnp.einsum("...gk,g->...k", prob, coords))
    return jnp.stack([*mus, alpha], axis=-1)


def heatmap_far_mass(heatmaps: Array, radius: float = 1.5) -> Array:
    """Share of each heatmap's mass farther than `radius` cells from its peak (a diagnostic of
    the softplus floor that pulls mu of Eq. 6 towards the grid centre; issue 15).

    Args:
        heatmaps: (..., g, g, g, K) non-negative heatmaps.
        radius: distance from the peak cell, in cells.

    Returns:
        (..., K) in [0, 1]: sum of the cells with |cell - peak| > radius / total mass.
    """
    if heatmaps.ndim < 4:
        raise ValueError(f"heatmap_far_mass: expected (..., g, g, g, K), got {heatmaps.shape}")
    g = heatmaps.shape[-2]
    flat = jnp.moveaxis(heatmaps, -1, -4).reshape(*heatmaps.shape[:-4], heatmaps.shape[-1], -1)
    peak = jnp.stack(jnp.unravel_index(jnp.argmax(flat, axis=-1), (g, g, g)), axis=-1)
    cells = jnp.stack(jnp.meshgrid(*[jnp.arange(g)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    dist2 = jnp.sum((cells - peak[..., None, :]) ** 2, axis=-1)  # (..., K, g^3)
    far = jnp.sum(jnp.where(dist2 > radius**2, flat, 0.0), axis=-1)
    return far / (jnp.sum(flat, axis=-1) + _EPS)


def gaussian_maps(keypoints: Array, sigma: float, n: int) -> Array:
    """Renders keypoints as isotropic gaussian maps on an n^3 grid (paper Eq. 7,
    docs/architecture.md §6).

    g_k(x) = alpha_k * prod_d exp(-(x_d - mu_kd)^2 / (2 (sigma / n)^2)), i.e. the width is `sigma`
    cells of the g-cell grid expressed as sigma / n in normalised units (the released
    convention; one cell is actually 2 / (n - 1) wide).

    Args:
        keypoints: (..., K, 4) xyz and alpha.
        sigma: width in cells (sigma_g of Tables 4-8).
        n: cells per axis of the output grid.

    Returns:
        (..., n, n, n, K) float32 maps.
    """
    coords = axis_coords(n)
    width = sigma / n
    mu = keypoints[..., :3]  # (..., K, 3)
    alpha = keypoints[..., 3]  # (..., K)
    # Separable: one 1-D profile per axis, then an outer product.
    profile = jnp.exp(-jnp.square(coords[:, None, None] - mu[..., None, :, :]) / (2 * width**2))
    # profile: (..., n, K, 3)
    px, py, pz = profile[..., 0], profile[..., 1], profile[..., 2]  # (..., n, K)
    maps = jnp.einsum("...ik,...jk,...lk->...ijlk", px, py, pz)
    return maps * alpha[..., None, None, None, :]


def affinity_from_params(params: Array) -> Array:
    """Eq. 12's decomposed affinities A_n from unconstrained parameters.

    Each row is a softmax over the K - 1 other keypoints, scattered into a K x K matrix with a zero
    diagonal: row i fills columns 0..i-1, i+1..K-1 in order.

    Args:
        params: (N, K, K-1) (any leading axes allowed: (..., K, K-1)).

    Returns:
        (..., K, K); rows sum to 1, diagonal 0.
    """
    k = params.shape[-2]
    if params.shape[-1] != k - 1:
        raise ValueError(f"affinity_from_params: expected (..., K, K-1) params, got {params.shape}")
    soft = jax.nn.softmax(params, axis=-1)
    rows = jnp.arange(k)[:, None]
    cols = jnp.arange(k)[None, :]
    source = jnp.clip(cols - (cols > rows), 0, max(k - 2, 0))  # column j<-param j, or j-1 past i
    gathered = jnp.take_along_axis(
        soft, jnp.broadcast_to(source, (*soft.shape[:-2], k, k)), axis=-1
    )
    return jnp.where(rows == cols, 0.0, gathered)


def influence(affinity: Array) -> Array:
    """The influence a_kk' = max_n A_n,kk' of the N decomposed affinities (docs/architecture.md §5,
    §7 step 1).

    The one definition behind the graph losses (Eqs. 13-16) and the skeleton extraction
    (Algorithm 1). It takes the array's own `max`, so a JAX array stays a JAX array (jit, grad)
    and a NumPy array stays NumPy in its dtype (float64 for Algorithm 1's exact tie-breaking).

    Args:
        affinity: (N, K, K), or an already combined (K, K), returned as it is.

    Returns:
        (K, K).
    """
    return affinity.max(axis=0) if affinity.ndim == 3 else affinity
