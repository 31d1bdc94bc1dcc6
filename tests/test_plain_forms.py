"""The detector's optimised forms against the plain formulations of `nmjax.models.reference`.

The real modules (`VoxelDecoder`, `FeatureNet`, `Conv3D`, `keypoints.gaussian_maps`) compute the
same function as the straightforward forms, in value and in the gradient with respect to the
parameters and every input, at tiny shapes: a change that breaks an optimisation in the model or
its kernels (`nmjax.models.conv_kernels`) shows here. The whole modules are compared, so the
pieces the optimisation benchmark times (`VoxelDecoder.input_features`, the CoordConv stem, the
stem and first pool, the convolutions after an upsampling) are checked inside them, and the
full-grid rewrites on their own, in every CPU form whatever the backend.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from nmjax import keypoints as kp_lib
from nmjax.models import blocks, conv_kernels, reference
from nmjax.models.conv_kernels import Evaluation
from nmjax.models.detector import VoxelDecoder

RNG = np.random.default_rng(0)


def normal(*shape: int) -> jax.Array:
    return jnp.asarray(RNG.normal(size=shape), jnp.float32)


def on_params(fn, module):
    """(fn as a function of the module's state, that state): the parameters become an input."""
    graphdef, state = nnx.split(module)
    return (lambda state, *inputs: fn(nnx.merge(graphdef, state), *inputs)), state


def value_and_grads(fn, *args):
    """fn(*args) and the gradient of sum(fn(*args) * r), r a fixed random cotangent, with respect
    to every argument."""

    def scalar(*args):
        y = fn(*args)
        return jnp.sum(y * jax.random.normal(jax.random.key(7), y.shape)), y

    grad_fn = jax.value_and_grad(scalar, argnums=tuple(range(len(args))), has_aux=True)
    (_, y), grads = jax.jit(grad_fn)(*args)
    return y, grads


def assert_same_function(fast, plain, *args):
    """`fast` and `plain` agree in value (to 1e-5 of the largest output) and in every gradient
    leaf (to 1e-4 of its largest entry; a conv bias before a GroupNorm has a gradient of float
    noise only, hence the floor at 1e-6 of the largest gradient of all)."""
    y_fast, g_fast = value_and_grads(fast, *args)
    y_plain, g_plain = value_and_grads(plain, *args)
    assert y_fast.shape == y_plain.shape
    np.testing.assert_allclose(y_fast, y_plain, atol=1e-5 * float(jnp.max(jnp.abs(y_plain))))
    leaves_fast, leaves_plain = jax.tree.leaves(g_fast), jax.tree.leaves(g_plain)
    largest = max(float(jnp.max(jnp.abs(g))) for g in leaves_plain)
    assert largest > 0
    for got, want in zip(leaves_fast, leaves_plain, strict=True):
        atol = 1e-4 * float(jnp.max(jnp.abs(want))) + 1e-6 * largest
        np.testing.assert_allclose(got, want, atol=atol)


@pytest.mark.parametrize("stride", [4, 2])
def test_decoder_convolves_the_context_once_per_crop_as_if_for_every_frame(stride):
    b, t, g, k, c = 1, 2, 2, 3, 8
    dec = VoxelDecoder(2 * k + c + 3, c, stride, rngs=nnx.Rngs(1))
    fast, params = on_params(VoxelDecoder.__call__, dec)
    plain, _ = on_params(reference.decoder, dec)
    maps, context = normal(b, t, g, g, g, k), normal(b, g, g, g, c + k + 3)
    assert_same_function(fast, plain, params, maps, context)


def test_feature_net_stem_equals_coordinates_concatenated_and_convolved():
    net = blocks.FeatureNet(8, (4, 4), 8, 4, rngs=nnx.Rngs(2))
    voxels = jnp.asarray(RNG.random((2, 8, 8, 8)) > 0.7, jnp.float32)
    fast, params = on_params(blocks.FeatureNet.__call__, net)
    plain, _ = on_params(reference.feature_net, net)
    assert_same_function(fast, plain, params, voxels)


def stem_and_pool(net: blocks.FeatureNet, voxels: jax.Array) -> jax.Array:
    """The first two layers of `net(voxels)`: the CoordConv stem, then the first pool."""
    return net.pool1(net.stem(voxels[..., None]))


# The stem's k=5 kernel: Winograd does not apply and takes the stacked form, so it is no case.
STEM_FORMS = [
    form
    for form in conv_kernels.CPU_FORMS
    if conv_kernels.resolve(form, "cpu", (8, 8, 8), 5, jnp.float32) == form
]


@pytest.mark.parametrize("form", STEM_FORMS)
def test_stem_and_pool_in_blocks_equal_them_on_the_full_grid(form):
    # A 2D form: the blocked path, whatever the backend.
    net = blocks.FeatureNet(8, (4, 4), 8, 4, evaluation=Evaluation(form), rngs=nnx.Rngs(5))
    net.stem.conv.bias[...] = jnp.array([0.3, -0.2])  # a bias shows up in the blocks' tiling
    voxels = jnp.asarray(RNG.random((2, 8, 8, 8)) > 0.7, jnp.float32)
    fast, params = on_params(stem_and_pool, net)
    plain, _ = on_params(reference.stem_and_pool, net)
    assert_same_function(fast, plain, params, voxels)


@pytest.mark.parametrize("form", conv_kernels.CPU_FORMS)
@pytest.mark.parametrize("shape", [(2, 3, 2, 4, 3), (1, 1, 1, 1, 2)])
def test_conv_after_upsampling_on_the_coarse_grid_equals_it_on_the_fine_grid(form, shape):
    block = blocks.ConvNormAct(
        shape[-1], 4, 3, upsample=True, evaluation=Evaluation(form), rngs=nnx.Rngs(6)
    )
    block.conv.bias[...] = jnp.array([0.5, -1.0, 2.0, 0.1])
    fast, params = on_params(blocks.ConvNormAct.__call__, block)
    plain, _ = on_params(reference.conv_after_upsampling, block)
    assert_same_function(fast, plain, params, normal(*shape))


@pytest.mark.parametrize("form", conv_kernels.CPU_FORMS)
def test_conv3d_in_2d_convolutions_equals_xla_3d_convolution(form):
    conv = blocks.Conv3D(2, 3, 3, evaluation=Evaluation(form), rngs=nnx.Rngs(3))
    conv.bias[...] = jnp.array([0.5, -1.0, 2.0])
    fast, params = on_params(blocks.Conv3D.__call__, conv)
    plain, _ = on_params(reference.conv3d, conv)
    assert_same_function(fast, plain, params, normal(2, 5, 4, 6, 2))


def test_separable_gaussian_maps_equal_the_dense_ones():
    keypoints = jnp.concatenate([0.4 * normal(2, 3, 4, 3), jnp.full((2, 3, 4, 1), 0.6)], -1)
    assert_same_function(
        lambda x: kp_lib.gaussian_maps(x, 1.5, 5),
        lambda x: reference.gaussian_maps(x, 1.5, 5),
        keypoints,
    )


def test_plain_gaussian_maps_against_numpy():
    kp = np.array([[0.1, -0.3, 0.5, 0.7], [-0.6, 0.2, 0.0, 1.0]], np.float32)
    n, sigma = 5, 1.5
    axis = np.linspace(-1, 1, n)
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    expected = np.stack(
        [
            a * np.exp(-((x - mx) ** 2 + (y - my) ** 2 + (z - mz) ** 2) / (2 * (sigma / n) ** 2))
            for mx, my, mz, a in kp
        ],
        axis=-1,
    )
    got = reference.gaussian_maps(jnp.asarray(kp), sigma, n)
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize(
    ("shape", "groups"),
    [((2, 4, 6, 2, 32), 2), ((3, 4, 4, 4, 8, 4), 1), ((2, 3, 5, 6), 3), ((1, 128, 8), 4)],
)
def test_group_norm_equals_flax_group_norm(shape, groups):
    """Cell counts with and without a factor of 64 (the folded sums), the block layout
    (B, X, Y, Z, 8, C), groups of several channels, one sample."""
    channels = shape[-1]
    ours = blocks.GroupNorm(channels, num_groups=groups, rngs=nnx.Rngs(0))
    ours.scale[...] = normal(channels)
    ours.bias[...] = normal(channels)
    flax_norm = nnx.GroupNorm(channels, num_groups=groups, rngs=nnx.Rngs(0))
    fast, params = on_params(blocks.GroupNorm.__call__, ours)
    plain, _ = on_params(nnx.GroupNorm.__call__, flax_norm)
    assert_same_function(fast, plain, params, 1.5 * normal(*shape) + 0.7)


def test_group_norm_against_numpy():
    x = np.asarray(3.0 * normal(2, 4, 4, 4, 6) - 2.0, np.float64)
    scale, bias = np.linspace(0.5, 2.0, 6), np.linspace(-1.0, 1.0, 6)
    groups = x.reshape(2, -1, 3, 2)  # (sample, cell, group, channel in group)
    mean = groups.mean(axis=(1, 3), keepdims=True)
    var = groups.var(axis=(1, 3), keepdims=True)
    expected = ((groups - mean) / np.sqrt(var + 1e-6)).reshape(x.shape) * scale + bias
    got = blocks.group_norm(
        jnp.asarray(x, jnp.float32),
        jnp.asarray(scale, jnp.float32),
        jnp.asarray(bias, jnp.float32),
        3,
        1e-6,
    )
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="4 groups do not divide 6 channels"):
        blocks.group_norm(jnp.asarray(x, jnp.float32), scale, bias, 4, 1e-6)
    with pytest.raises(ValueError, match="no mask"):
        blocks.GroupNorm(6, num_groups=3, rngs=nnx.Rngs(0))(jnp.asarray(x), mask=x > 0)


def test_group_norm_gradient_against_float64_over_many_cells():
    """The hand-written VJP, jitted, against the float64 gradient with 2^18 cells per sample (the
    full grid at G=64) and a mean offset: every gradient within 1e-5 of float64."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=(3, 64, 64, 64, 4)) + 2.0
    g = rng.normal(size=x.shape)
    scale, bias = rng.normal(size=4), rng.normal(size=4)
    groups = x.reshape(3, -1, 2, 2)  # (sample, cell, group, channel in group)
    mean = groups.mean(axis=(1, 3), keepdims=True)
    inv = 1.0 / np.sqrt(groups.var(axis=(1, 3), keepdims=True) + 1e-6)
    xhat = (groups - mean) * inv
    g_groups = g.reshape(groups.shape)
    d_xhat = g_groups * scale.reshape(1, 1, 2, 2)
    d_x = inv * (
        d_xhat
        - d_xhat.mean(axis=(1, 3), keepdims=True)
        - xhat * (d_xhat * xhat).mean(axis=(1, 3), keepdims=True)
    )
    expected = (
        d_x.reshape(x.shape),
        (g_groups * xhat).reshape(-1, 4).sum(0),
        g.reshape(-1, 4).sum(0),
    )
    f32 = [jnp.asarray(a, jnp.float32) for a in (x, scale, bias, g)]
    grads = jax.jit(lambda *a: jax.vjp(lambda *p: blocks.group_norm(*p, 2, 1e-6), *a[:3])[1](a[3]))
    for got, want in zip(grads(*f32), expected, strict=True):
        err = np.linalg.norm(np.asarray(got, np.float64) - want) / np.linalg.norm(want)
        assert err < 1e-5
