"""The detector is the released network (docs/architecture.md §6): its layers, activations, norms
and initialisation pinned without the release itself (parameter counts from its C = 128 network)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import release_files as rf
from flax import nnx

from nmjax.config import skel_preset
from nmjax.models import blocks, conv_kernels
from nmjax.models.detector import KeypointDetector


def _param_count(model: nnx.Module) -> int:
    return sum(int(np.prod(x.shape)) for x in jax.tree.leaves(nnx.state(model, nnx.Param)))


def _default_detector(k: int) -> KeypointDetector:
    cfg = dataclasses.replace(skel_preset("synth-arm", "default").model, num_keypoints=k)
    return KeypointDetector(cfg, rngs=nnx.Rngs(0))


@pytest.fixture(scope="module")
def default_detector():
    return _default_detector(12)


def test_parameter_counts_equal_the_releases_at_the_default_preset(default_detector):
    # The release's detector at C = 128, hourglass (32, 48, 72), N = 2 affinities.
    assert _param_count(default_detector) == 8_548_500
    assert _param_count(_default_detector(24)) == 8_557_044
    assert _param_count(_default_detector(28)) == 8_560_020


def _rand(key: int, shape: tuple[int, ...]) -> jax.Array:
    return jax.random.normal(jax.random.key(key), shape)


def _larger_weights(module: nnx.Module, seed: int = 0) -> nnx.Module:
    """`module` with every conv kernel redrawn at unit scale, so activations are not ~0."""
    module = nnx.clone(module)
    for i, (_, m) in enumerate(nnx.iter_modules(module)):
        if isinstance(m, blocks.Conv3D):
            m.kernel[...] = _rand(seed + i, m.kernel[...].shape) * 0.3
    return module


def test_leaky_relu_has_pytorchs_default_slope():
    assert blocks.LEAK == 0.01
    block = _larger_weights(blocks.ConvNormAct(3, 4, 3, rngs=nnx.Rngs(0)))
    x = _rand(1, (2, 4, 4, 4, 3))
    normed = np.asarray(block.norm(block.conv(x)))
    out = np.asarray(block(x))
    neg = normed < 0
    assert neg.any() and (~neg).any()
    np.testing.assert_allclose(out[neg], 0.01 * normed[neg], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(out[~neg], normed[~neg], rtol=1e-6)


@pytest.mark.parametrize(("cin", "cout"), [(4, 4), (4, 8)])
def test_residual_block_returns_branch_plus_skip_without_activation(cin, cout):
    block = _larger_weights(blocks.ResBlock(cin, cout, rngs=nnx.Rngs(0)))
    x = _rand(2, (2, 4, 4, 4, cin))
    branch = block.norm2(block.conv2(block.conv1(x)))
    skip = x if block.skip is None else block.skip(x)
    out = np.asarray(block(x))
    np.testing.assert_allclose(out, np.asarray(branch + skip), rtol=1e-6, atol=1e-6)
    assert (out < -0.1).mean() > 0.1  # no activation after the sum: clearly negative values


def test_projection_skip_is_a_1x1x1_conv_then_groupnorm():
    block = blocks.ResBlock(4, 8, rngs=nnx.Rngs(0))
    assert blocks.ResBlock(4, 4, rngs=nnx.Rngs(0)).skip is None  # identity at equal widths
    assert block.skip.conv.kernel[...].shape == (1, 1, 1, 4, 8)
    assert isinstance(block.skip.norm, blocks.GroupNorm)
    x = _rand(3, (2, 4, 4, 4, 4))
    y = block.skip.conv(x)
    np.testing.assert_allclose(block.skip(x), block.skip.norm(y), rtol=1e-6)
    # Normalised: per sample, each group of channels has mean 0 and variance ~1.
    groups = np.asarray(block.skip(x)).reshape(2, -1, block.skip.norm.num_groups, 8 // 1)
    assert np.abs(groups.mean()) < 1e-5


def test_hourglass_has_a_residual_block_before_every_upsampling():
    hg = blocks.Hourglass(64, (32, 48, 72), 16, rngs=nnx.Rngs(0))

    def widths(res):
        return res.conv1.conv.kernel[...].shape[3:]

    assert [widths(d.res) for d in hg.down] == [(64, 32), (32, 48), (48, 72)]
    assert [widths(s) for s in hg.skips] == [(64, 64), (32, 32), (48, 48)]
    assert [widths(r) for r in hg.up_res] == [(72, 72), (48, 48), (32, 32)]
    assert [u.conv.kernel[...].shape[3:] for u in hg.up] == [(72, 48), (48, 32), (32, 64)]
    # The layers under the release's names, and the hourglass against its flat program.
    layers = _release_hourglass_layers(hg)
    released = {
        name.split(".")[4]
        for name in rf.release_shapes()
        if name.startswith("kypt_detector.vox_to_kypt.extract_features.4.")
    }
    assert set(layers) == released
    x = _rand(4, (1, 16, 16, 16, 64)) * 0.1

    @nnx.jit  # one compiled program each: op by op, the hourglass takes minutes
    def by_program(hg, x):
        named, kept = _release_hourglass_layers(hg), {}
        for step in HOURGLASS_PROGRAM:
            action, _, name = step.rpartition(" ")
            if action == "keep":
                kept[name] = named[name](x)
            elif action == "add":
                x = x + kept[name]
            else:
                x = named[name](x)
        return x

    whole = nnx.jit(lambda hg, x: hg(x))(hg, x)
    np.testing.assert_allclose(whole, by_program(hg, x), rtol=1e-5, atol=1e-6)


# The three-level hourglass of paper Fig. 9 as one flat program over the release's layer names
# (level 1 at the input resolution, shared/release/aist_state_dict.tsv): "keep L" sets aside
# L(x) of the current x, "add L" adds what was set aside. Written out step by step so that it
# shares no loop or ordering with `Hourglass.__call__`.
HOURGLASS_PROGRAM = (
    "keep skip_res1",
    "encoder_pool1",
    "encoder_res1",
    "keep skip_res2",
    "encoder_pool2",
    "encoder_res2",
    "keep skip_res3",
    "encoder_pool3",
    "encoder_res3",
    "decoder_res3",
    "decoder_upsample3",
    "add skip_res3",
    "decoder_res2",
    "decoder_upsample2",
    "add skip_res2",
    "decoder_res1",
    "decoder_upsample1",
    "add skip_res1",
)


def _release_hourglass_layers(hg: blocks.Hourglass) -> dict[str, nnx.Module]:
    """The hourglass's layers by the release's names: its module lists hold level l (1-based)
    at index l - 1 going down and at index L - l coming up (the widths pin which is which)."""
    levels = len(hg.down)
    layers = {}
    for level in range(1, levels + 1):
        layers[f"encoder_pool{level}"] = hg.down[level - 1].pool
        layers[f"encoder_res{level}"] = hg.down[level - 1].res
        layers[f"skip_res{level}"] = hg.skips[level - 1]
        layers[f"decoder_res{level}"] = hg.up_res[levels - level]
        layers[f"decoder_upsample{level}"] = hg.up[levels - level]
    return layers


def test_groupnorm_epsilon_is_pytorchs_default(default_detector):
    norms = [m for _, m in nnx.iter_modules(default_detector) if isinstance(m, blocks.GroupNorm)]
    assert norms and all(n.epsilon == 1e-5 for n in norms)
    # eps matters where the variance is small: (x - mean) / sqrt(var + 1e-5).
    x = jnp.asarray([0.0, 2e-3, -2e-3, 0.0]).reshape(1, 4, 1)  # var 2e-6, below eps
    out = conv_kernels.group_norm(x, jnp.ones(1), jnp.zeros(1), 1, blocks.GN_EPS)
    var = np.var(np.asarray(x))
    np.testing.assert_allclose(out[0, 1, 0], 2e-3 / np.sqrt(var + 1e-5), rtol=1e-4)
    assert abs(float(out[0, 1, 0]) - 2e-3 / np.sqrt(var + 1e-6)) > 0.5  # flax's 1e-6 differs


def test_heads_can_go_negative_while_the_fused_heatmap_stays_positive():
    cfg = skel_preset("synth-arm", "tiny").model
    model = KeypointDetector(cfg, rngs=nnx.Rngs(0))
    voxels = (jax.random.uniform(jax.random.key(5), (1, 4, 16, 16, 16)) > 0.7).astype(jnp.float32)

    @nnx.jit  # one compiled program: op by op, the detector's many operations take minutes
    def head_and_fused(model, voxels):
        head = nnx.leaky_relu(model.heat(model.features(voxels[0])), blocks.LEAK)
        return head, model.detect(voxels)[0]

    head, heatmaps = head_and_fused(model, voxels)
    head = np.asarray(head)
    assert (head < 0).any()
    assert np.all(np.asarray(heatmaps) > 0)
    # The head ends in the LeakyReLU: exactly the detector's frame branch before the fusion.
    model.fuse.kernel[...] = jnp.asarray([[1.0], [0.0]])
    model.fuse.bias[...] = jnp.zeros(1)
    fused = head_and_fused(model, voxels)[1]
    np.testing.assert_allclose(
        np.asarray(fused[0]), np.asarray(jax.nn.softplus(jnp.asarray(head))), rtol=1e-5, atol=1e-6
    )


def test_initialisation_is_the_releases(default_detector):
    model = default_detector
    in_features, outside = [], []
    for path, m in nnx.iter_modules(model):
        if isinstance(m, blocks.Conv3D):
            (in_features if path[0] in ("features", "st_features") else outside).append(m)
        if isinstance(m, blocks.GroupNorm):
            np.testing.assert_array_equal(m.scale[...], 1.0)
            np.testing.assert_array_equal(m.bias[...], 0.0)
    # Per feature net: stem, 2 pools, 2 residual blocks with projection (3 convs each), and the
    # hourglass's 3 levels of pool + projected residual (4), 3 skips and 3 up residuals (2 each),
    # 3 upsamplings: 36. Outside: the two heads and the decoder's 6 convolutions.
    assert len(in_features) == 2 * 36 and len(outside) == 2 + 6
    for m in in_features + outside:
        np.testing.assert_array_equal(m.bias[...], 0.0)
    for convs, std in ((in_features, 0.001), (outside, 0.02)):
        for m in convs:
            w = np.asarray(m.kernel[...])
            # The std of n normal draws is within 5 / sqrt(2 n) of the true one (5 sigma).
            assert abs(w.std() / std - 1) < 5 / np.sqrt(2 * w.size) + 1e-3, (m.kernel.shape, std)
            assert abs(w.mean()) < 5 * std / np.sqrt(w.size)
    fuse = np.asarray(model.fuse.kernel[...])
    assert fuse.shape == (2, 1) and np.all(np.abs(fuse) < 0.1) and np.any(fuse != 0)
    np.testing.assert_array_equal(model.fuse.bias[...], 0.0)
    np.testing.assert_array_equal(model.affinity_params[...], 1.0)


def test_fan_in_initialisation_is_a_named_option_that_spreads_untrained_keypoints():
    cfg = dataclasses.replace(skel_preset("synth-arm", "tiny").model, grid=16)
    models = {
        init: KeypointDetector(dataclasses.replace(cfg, init=init), rngs=nnx.Rngs(0))
        for init in ("release", "fan_in")
    }
    convs = [m for _, m in nnx.iter_modules(models["fan_in"]) if isinstance(m, blocks.Conv3D)]
    assert len(convs) > 10
    for m in convs:
        w = np.asarray(m.kernel[...])
        std = 1 / np.sqrt(np.prod(w.shape[:-1]))
        assert abs(w.std() / std - 1) < 5 / np.sqrt(2 * w.size) + 1e-3, w.shape
        np.testing.assert_array_equal(m.bias[...], 0.0)
    np.testing.assert_array_equal(models["fan_in"].fuse.kernel[...], [[1.0], [0.0]])
    np.testing.assert_array_equal(models["fan_in"].fuse.bias[...], [-4.0])
    # What the option is for: at the release's scales an untrained detector puts every keypoint
    # in one spot; at fan-in scale they spread.
    voxels = jnp.asarray(np.random.default_rng(0).random((1, 2, 16, 16, 16)) < 0.1, jnp.float32)
    spread = {
        init: float(
            np.asarray(nnx.jit(lambda m, v: m(v)["keypoints"])(model, voxels))[..., :3]
            .std(axis=2)
            .mean()
        )
        for init, model in models.items()
    }
    assert spread["release"] < 0.01 < 0.05 < spread["fan_in"], spread
    with pytest.raises(ValueError, match="model.init"):
        KeypointDetector(dataclasses.replace(cfg, init="xavier"), rngs=nnx.Rngs(0))
