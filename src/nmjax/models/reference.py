"""The plain formulations of what the detector computes in an optimised form: the reference.

Each function takes a real module of `nmjax.models` (its parameters) and computes what
docs/architecture.md §6 writes down, the straightforward way, with none of the model's shortcuts:
every convolution is XLA's own 3D convolution (`conv_kernels.conv3d_native`) on the full grid it is
printed on. The model never calls them; they are what its fast forms are held to.
tests/test_plain_forms.py checks the model against them in value and gradient;
experiments/bench_optimisations.py times the model against them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import nnx

from nmjax.keypoints import coord_grid
from nmjax.models.blocks import LEAK, Conv3D, ConvNormAct, FeatureNet
from nmjax.models.conv_kernels import conv3d_native
from nmjax.models.detector import VoxelDecoder


def conv3d(conv: Conv3D, x: jax.Array, op: str = "same") -> jax.Array:
    """A stride-1 `Conv3D` as XLA's own 3D convolution ('SAME') plus the bias; op "coords" with
    the coordinate channels concatenated first, "upsampled" on the trilinearly upsampled input.

    x (B, X, Y, Z, Ci) -> (B, X', Y', Z', Co): X' = X, or 2 X for "upsampled".
    """
    return conv3d_native(x, conv.kernel[...], op) + conv.bias[...]


def stem_conv(net: FeatureNet, voxels: jax.Array) -> jax.Array:
    """CoordConv as printed: [occupancy, x, y, z] concatenated to every sample, then one 3D conv.

    voxels (B, G, G, G) -> (B, G, G, G, C/4), as `net.stem.conv(voxels[..., None])`.
    """
    return conv3d(net.stem.conv, voxels[..., None], "coords")


def stem_and_pool(net: FeatureNet, voxels: jax.Array) -> jax.Array:
    """The stem (conv5 + GroupNorm + LeakyReLU) on the full grid, then the first strided pool.

    voxels (B, G, G, G) -> (B, G/2, G/2, G/2, C/4), as the first two blocks of `net(voxels)`.
    """
    return net.pool1(nnx.leaky_relu(net.stem.norm(stem_conv(net, voxels)), LEAK))


def feature_net(net: FeatureNet, voxels: jax.Array) -> jax.Array:
    """f_feat with the plain stem on the full grid, then the first pool on it; the blocks after
    it are the net's own. voxels (B, G, G, G) -> (B, g, g, g, C), as `net(voxels)`."""
    x = net.res1(stem_and_pool(net, voxels))
    x = x if net.pool2 is None else net.pool2(x)
    return net.res2(net.hourglass(x))


def decoder_input(dec: VoxelDecoder, maps: jax.Array, context: jax.Array) -> jax.Array:
    """The decoder's input 1x1x1 conv + LeakyReLU on [g_t, context] concatenated for every frame.

    maps (B, T, g, g, g, K), context (B, g, g, g, C + K + 3) -> (B, T, g, g, g, C), as
    `dec.input_features`.
    """
    every_frame = jnp.broadcast_to(context[:, None], (*maps.shape[:2], *context.shape[1:]))
    return nnx.leaky_relu(dec.inp(jnp.concatenate([maps, every_frame], axis=-1)), LEAK)


def conv_after_upsampling(block: ConvNormAct, x: jax.Array) -> jax.Array:
    """The trilinear 2x upsampling, then the block's conv, GroupNorm and LeakyReLU on the
    upsampled grid, as an upsampling `block(x)`: x (B, X, Y, Z, Ci) -> (B, 2X, 2Y, 2Z, Co)."""
    return nnx.leaky_relu(block.norm(conv3d(block.conv, x, "upsampled")), LEAK)


def decoder(dec: VoxelDecoder, maps: jax.Array, context: jax.Array) -> jax.Array:
    """f_dec with the plain input conv and every convolution after an upsampling on the
    upsampled grid; the blocks are the decoder's own.

    maps (B, T, g, g, g, K), context (B, g, g, g, C + K + 3) -> (B, T, G, G, G) raw logits, as
    `dec(maps, context)`.
    """
    b, t = maps.shape[:2]
    x = decoder_input(dec, maps, context)
    x = x.reshape(b * t, *x.shape[2:])
    first, second = dec.up1.layers
    x = second(conv_after_upsampling(first, x) if dec.upsample_first else first(x))
    first, second = dec.up2.layers
    x = second(conv_after_upsampling(first, x))
    return dec.out(x)[..., 0].reshape(b, t, *x.shape[1:4])


def gaussian_maps(keypoints: jax.Array, sigma: float, n: int) -> jax.Array:
    """Eq. 7's maps alpha exp(-||x - mu||^2 / (2 (sigma / n)^2)), dense over the n^3 grid.

    keypoints (..., K, 4) -> (..., n, n, n, K), as `keypoints.gaussian_maps`.
    """
    grid = coord_grid(n)[..., None, :]  # (n, n, n, 1, 3)
    mu = keypoints[..., None, None, None, :, :3]  # (..., 1, 1, 1, K, 3)
    alpha = keypoints[..., None, None, None, :, 3]
    return alpha * jnp.exp(-jnp.sum(jnp.square(grid - mu), axis=-1) / (2 * (sigma / n) ** 2))
