"""Tests of the keypoint detector and its 3D layers (nmjax.models.blocks, nmjax.models.detector);
their kernels are tested in test_conv_kernels.py."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from nmjax.config import skel_preset
from nmjax.config_io import config_from_dict, config_to_dict
from nmjax.models import blocks
from nmjax.models.conv_kernels import Evaluation
from nmjax.models.detector import KeypointDetector, check_detector_config


def test_detector_value_and_gradient_do_not_depend_on_the_conv_forms():
    """The whole phase-1 loss and its gradient with XLA's 3D convolution everywhere
    (model.conv_form = "native"), against "auto": on CPU the code's CPU forms (Winograd's, taps
    stacked where it does not apply, the blocked stem, the fused upsampling convolutions); on
    GPU/TPU "auto" is the native convolution too, and the test checks only that two models of
    one configuration and seed compute the same (the CPU forms on other backends are compared in
    test_conv_kernels.py and test_plain_forms.py, named explicitly)."""
    from nmjax import losses

    cfg = skel_preset("synth-arm", "tiny")
    model_cfg = dataclasses.replace(
        cfg.model, grid=8, channels=4, num_keypoints=4, hourglass_channels=(4, 4, 4)
    )
    rng = np.random.default_rng(6)
    voxels = jnp.asarray(rng.random((1, 3, 8, 8, 8)) > 0.7, jnp.float32)

    def value_and_grad(form):
        model_form = dataclasses.replace(model_cfg, conv_form=form)
        graphdef, params = nnx.split(KeypointDetector(model_form, rngs=nnx.Rngs(0)))

        def loss(params):
            outputs = nnx.merge(graphdef, params)(voxels)
            return losses.skeleton_loss({"voxels": voxels, **outputs}, cfg.weights)[0]

        return jax.jit(jax.value_and_grad(loss))(params)

    results = {form: value_and_grad(form) for form in ("native", "auto")}
    (v0, g0), (v1, g1) = results["native"], results["auto"]
    assert float(v1) == pytest.approx(float(v0), rel=1e-5)
    leaves0, leaves1 = jax.tree.leaves(g0), jax.tree.leaves(g1)
    norm = np.sqrt(sum(float(jnp.sum(a**2)) for a in leaves0))
    diff = np.sqrt(sum(float(jnp.sum((a - b) ** 2)) for a, b in zip(leaves0, leaves1, strict=True)))
    assert diff <= 1e-4 * norm


def test_strided_pool_and_transposed_conv_match_definitions():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(1, 4, 6, 2, 3)).astype(np.float32)
    pool = blocks.Conv3D(3, 5, 2, 2, rngs=nnx.Rngs(0))
    w = np.asarray(pool.kernel[...])
    expected = np.zeros((1, 2, 3, 1, 5))
    for i, j, k in np.ndindex(2, 3, 1):
        block = x[0, 2 * i : 2 * i + 2, 2 * j : 2 * j + 2, 2 * k : 2 * k + 2]  # (2,2,2,3)
        expected[0, i, j, k] = np.einsum("abci,abcio->o", block, w)
    np.testing.assert_allclose(pool(jnp.asarray(x)), expected, atol=1e-5)

    up = blocks.Conv3D(3, 5, 2, 2, transpose=True, rngs=nnx.Rngs(1))
    w = np.asarray(up.kernel[...])
    expected = np.zeros((1, 8, 12, 4, 5))
    for i, j, k in np.ndindex(4, 6, 2):  # every input cell paints its own 2x2x2 output block
        expected[0, 2 * i : 2 * i + 2, 2 * j : 2 * j + 2, 2 * k : 2 * k + 2] = np.einsum(
            "i,abcio->abco", x[0, i, j, k], w
        )
    np.testing.assert_allclose(up(jnp.asarray(x)), expected, atol=1e-5)
    # Also the adjoint of the strided conv with the same kernel, as a transposed conv must be.
    y = rng.normal(size=(1, 2, 3, 1, 3)).astype(np.float32)
    down = blocks.Conv3D(3, 3, 2, 2, rngs=nnx.Rngs(3))
    upt = blocks.Conv3D(3, 3, 2, 2, transpose=True, rngs=nnx.Rngs(3))
    upt.kernel[...] = jnp.swapaxes(down.kernel[...], -1, -2)
    lhs = jnp.vdot(down(jnp.asarray(x)) - down.bias[...], y)
    rhs = jnp.vdot(jnp.asarray(x), upt(jnp.asarray(y)) - upt.bias[...])
    assert float(lhs) == pytest.approx(float(rhs), rel=1e-4)


def test_conv_form_is_a_field_of_the_configuration_that_reaches_every_convolution():
    """model.conv_form is recorded in config.json (as `config_to_dict` writes it), read back, and
    every `Conv3D` of the detector built from it evaluates in that form, with the dtype of
    model.compute_dtype; an unknown name is refused with the field's name."""
    assert skel_preset("synth-arm", "cpu").model.conv_form == "auto"
    assert skel_preset("synth-arm", "default").model.conv_form == "auto"
    cfg = skel_preset("synth-arm", "tiny")
    assert cfg.model.conv_form == "stacked"  # compiles quickest (config.skel_preset)
    cfg = dataclasses.replace(
        cfg, model=dataclasses.replace(cfg.model, conv_form="per_tap", compute_dtype="bfloat16")
    )
    stored = config_to_dict(cfg)
    assert stored["model"]["conv_form"] == "per_tap"
    back = config_from_dict(type(cfg), stored)
    model = KeypointDetector(back.model, rngs=nnx.Rngs(0))
    convs = [m for _, m in nnx.iter_modules(model) if isinstance(m, blocks.Conv3D)]
    assert convs and {c.evaluation for c in convs} == {Evaluation("per_tap", "bfloat16")}
    assert {c.op for c in convs} == {"same", "strided", "transposed", "upsampled", "coords"}
    bad = dataclasses.replace(cfg.model, conv_form="fast")
    with pytest.raises(ValueError, match="model.conv_form"):
        check_detector_config(bad)


def test_conv3d_refuses_upsampling_or_coordinates_with_strides():
    with pytest.raises(ValueError, match="upsample or coords"):
        blocks.Conv3D(1, 1, 2, 2, upsample=True, rngs=nnx.Rngs(0))
    with pytest.raises(ValueError, match="upsample or coords"):
        blocks.Conv3D(4, 1, 3, coords=True, upsample=True, rngs=nnx.Rngs(0))


def test_hourglass_levels():
    assert blocks.hourglass_levels(16, 3) == 3
    assert blocks.hourglass_levels(8, 3) == 3
    assert blocks.hourglass_levels(4, 3) == 2
    assert blocks.hourglass_levels(6, 3) == 1
    assert blocks.hourglass_levels(2, 0) == 0


# The detector's forward pass compiled as one program: run op by op, its thousands of small
# operations each compile on their own, which takes minutes.
_forward = nnx.jit(lambda model, voxels: model(voxels))


@pytest.fixture(scope="module", params=[4, 2], ids=["stride4", "stride2"])
def tiny_outputs(request):
    cfg = skel_preset("synth-arm", "tiny")
    cfg = dataclasses.replace(
        cfg, model=dataclasses.replace(cfg.model, heatmap_stride=request.param)
    )
    model = KeypointDetector(cfg.model, rngs=nnx.Rngs(0))
    b, t, g = cfg.data.batch_size, cfg.data.frames, cfg.model.grid
    voxels = (jax.random.uniform(jax.random.key(1), (b, t, g, g, g)) > 0.8).astype(jnp.float32)
    return cfg, model, voxels, _forward(model, voxels)


def test_detector_output_shapes_and_ranges(tiny_outputs):
    cfg, _, voxels, out = tiny_outputs
    b, t, g = cfg.data.batch_size, cfg.data.frames, cfg.model.grid
    k, n = cfg.model.num_keypoints, cfg.model.num_affinity
    h = g // cfg.model.heatmap_stride
    assert "voxels" not in out  # the detector returns its outputs, not its input
    assert out["recon"].shape == (b, t, g, g, g)
    assert out["heatmaps"].shape == (b, t, h, h, h, k)
    assert out["keypoints"].shape == (b, t, k, 4)
    assert out["affinity"].shape == (n, k, k)
    assert all(v.dtype == jnp.float32 for v in out.values())
    recon = np.asarray(out["recon"])
    assert np.all((recon >= 0) & (recon <= 1))
    assert np.all(np.asarray(out["heatmaps"]) > 0)  # softplus after the fusion
    kp = np.asarray(out["keypoints"])
    assert np.all(np.abs(kp[..., :3]) <= 1.0 + 1e-6)
    assert np.all((kp[..., 3] >= 0) & (kp[..., 3] <= 1 + 1e-6))
    np.testing.assert_allclose(kp[..., 3].max(axis=-1), 1.0, atol=1e-4)
    # Affinity parameters start at ones: every off-diagonal entry is 1 / (K - 1).
    aff = np.asarray(out["affinity"])
    expected = (np.ones((k, k)) - np.eye(k)) / (k - 1)
    np.testing.assert_allclose(aff, np.broadcast_to(expected, aff.shape), atol=1e-6)


def test_decoder_is_relative_to_first_frame(tiny_outputs):
    cfg, model, voxels, _ = tiny_outputs
    model = nnx.clone(model)
    model.decoder.out.kernel[...] = jnp.zeros_like(model.decoder.out.kernel[...])
    model.decoder.out.bias[...] = jnp.zeros_like(model.decoder.out.bias[...])
    recon = np.asarray(_forward(model, voxels)["recon"])
    # raw = 0 -> v_hat_t = sigmoid(10 (v_1 - 0.5)) for every frame t (Eq. 7 with tanh(0) = 0).
    v1 = np.asarray(voxels[:, :1])
    expected = 1.0 / (1.0 + np.exp(-cfg.model.decoder_sharpness * (v1 - 0.5)))
    np.testing.assert_allclose(recon, np.broadcast_to(expected, recon.shape), atol=1e-6)


def test_frames_are_independent_except_through_temporal_mean(tiny_outputs):
    _, model, voxels, out = tiny_outputs
    # Swapping two frames (t >= 1) keeps the temporal mean and frame 1: outputs swap with them.
    perm = np.arange(voxels.shape[1])
    perm[[1, 2]] = perm[[2, 1]]
    swapped = _forward(model, voxels[:, perm])
    np.testing.assert_allclose(swapped["keypoints"], out["keypoints"][:, perm], atol=1e-5)
    np.testing.assert_allclose(swapped["recon"], out["recon"][:, perm], atol=1e-5)


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("num_keypoints", 1, "num_keypoints"),
        ("grid", 18, "multiple of 4"),
        ("channels", 2, "C"),
        ("heatmap_stride", 8, "heatmap_stride"),
    ],
)
def test_bad_detector_config(field, value, match):
    cfg = dataclasses.replace(skel_preset("synth-arm", "tiny").model, **{field: value})
    with pytest.raises(ValueError, match=match):
        check_detector_config(cfg)
    with pytest.raises(ValueError, match=match):
        KeypointDetector(cfg, rngs=nnx.Rngs(0))


def test_detector_rejects_wrong_voxel_shape(tiny_outputs):
    _, model, voxels, _ = tiny_outputs
    with pytest.raises(ValueError, match="expected voxels"):
        model(voxels[..., :-1])
