"""Tests of the keypoint detector and its 3D blocks (nmjax.models.blocks, nmjax.models.detector)."""

from __future__ import annotations

import dataclasses
import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from nmjax.config import skel_preset
from nmjax.models import blocks
from nmjax.models.detector import KeypointDetector, check_detector_config


def _reference_conv_same(x, w):
    """NumPy 'SAME' stride-1 cross-correlation, x (B,X,Y,Z,Ci), w (k,k,k,Ci,Co)."""
    k = w.shape[0]
    p = k // 2
    xp = np.pad(x, ((0, 0), (p, p), (p, p), (p, p), (0, 0)))
    nx, ny, nz = x.shape[1:4]
    out = np.zeros((*x.shape[:4], w.shape[-1]))
    for a in range(k):
        for b in range(k):
            for c in range(k):
                window = xp[:, a : a + nx, b : b + ny, c : c + nz]
                out += np.einsum("...i,io->...o", window, w[a, b, c])
    return out


def _jaxpr(fn, *args) -> str:
    return str(jax.make_jaxpr(fn)(*args))


def _conv_count(fn, *args) -> int:
    return _jaxpr(fn, *args).count("conv_general_dilated")


@pytest.mark.parametrize("kernel", [1, 3, 5])
@pytest.mark.parametrize("form", ["native", *blocks.CPU_FORMS])
def test_conv3d_same_matches_numpy(kernel, form):
    conv = blocks.Conv3D(2, 3, kernel, rngs=nnx.Rngs(0))
    blocks.set_conv_form(conv, form)
    conv.bias[...] = jnp.array([0.5, -1.0, 2.0])
    x = np.random.default_rng(1).normal(size=(2, 6, 5, 4, 2)).astype(np.float32)
    expected = _reference_conv_same(x, np.asarray(conv.kernel[...])) + [0.5, -1.0, 2.0]
    np.testing.assert_allclose(conv(jnp.asarray(x)), expected, atol=1e-4)


@pytest.mark.parametrize("kernel", [3, 5])
def test_conv3d_same_forms_agree_in_value_and_gradient(kernel):
    rng = np.random.default_rng(4)
    x = jnp.asarray(rng.normal(size=(2, 6, 5, 4, 3)), jnp.float32)
    w = jnp.asarray(rng.normal(size=(kernel, kernel, kernel, 3, 4)), jnp.float32)
    cotangent = jnp.asarray(rng.normal(size=(2, 6, 5, 4, 4)), jnp.float32)

    def loss(x, w, form):
        return jnp.sum(blocks.conv3d_same(x, w, form) * cotangent)

    results = {}
    winograd_convs = 0 if kernel == 3 else 1  # k=5 falls back to the stacked form
    for form, convs in (
        ("native", 1),
        ("per_tap", kernel),
        ("stacked", 1),
        ("winograd", winograd_convs),
    ):
        conv = functools.partial(blocks.conv3d_same, form=form)
        assert _conv_count(conv, x, w) == convs, form
        grads = jax.grad(loss, argnums=(0, 1))(x, w, form)
        results[form] = (conv(x, w), *grads)
    for form in blocks.CPU_FORMS:
        for got, want in zip(results[form], results["native"], strict=True):
            if form == "winograd" and kernel == 3:  # about 1e-5 of the largest value
                atol = 2e-5 * float(jnp.max(jnp.abs(want)))
                np.testing.assert_allclose(got, want, atol=atol, err_msg=form)
            else:
                np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-4, err_msg=form)


def test_conv3d_same_stacks_the_taps_into_one_2d_convolution_on_cpu():
    """Where "auto" does not take Winograd's form on CPU (grids under WINOGRAD_MIN_SIDE, k=5,
    bfloat16), one 2D convolution with the k taps stacked, never XLA's 3D convolution."""
    rng = np.random.default_rng(5)
    side = blocks.WINOGRAD_MIN_SIDE
    cases = [(3, 1, 4, jnp.float32, 4), (3, 16, 64, jnp.float32, 4), (3, 128, 128, jnp.float32, 4)]
    cases += [(5, 1, 4, jnp.float32, side), (3, 8, 8, jnp.bfloat16, side)]
    for k, ci, co, dtype, n in cases:  # the stem, a coarse decoder conv, the paper's widths
        x = jnp.zeros((1, n, n, n, ci), dtype)
        w = jnp.asarray(rng.normal(size=(k, k, k, ci, co)), dtype)
        jaxpr = _jaxpr(blocks.conv3d_same, x, w)
        assert jaxpr.count("conv_general_dilated") == 1, ci  # not one per tap
        assert jaxpr.count("window_strides=(1, 1)") == 1, ci  # 2D, never XLA's 3D on CPU
        assert f"{k},{k},{k * ci},{co}]" in jaxpr.replace(" ", ""), ci  # the k-deep kernel


def test_conv3d_same_takes_winograds_form_on_cpu_for_float32_3x3x3_on_large_grids():
    side = blocks.WINOGRAD_MIN_SIDE
    x = jnp.zeros((2, side, side + 2, side, 16), jnp.float32)
    w = jnp.zeros((3, 3, 3, 16, 32), jnp.float32)
    jaxpr = _jaxpr(blocks.conv3d_same, x, w)
    assert "conv_general_dilated" not in jaxpr
    # 216 tile positions, each one matmul over B * tiles = 2 * 2 * 3 * 2 rows
    assert "f32[216,24,32]" in jaxpr.replace(" ", "")
    assert _conv_count(blocks.conv3d_same, x[:, :, :4], w) == 1  # a side under the minimum


@pytest.mark.parametrize("shape", [(2, 8, 8, 8, 3), (1, 9, 12, 5, 2), (1, 1, 2, 3, 1)])
def test_winograd_conv_matches_float64_in_value_and_gradient(shape):
    """F(4x4x4, 3x3x3) in float32 against the direct sum in float64: within 2e-5 of the
    largest value (the interpolation points +-2 cost digits the direct forms keep)."""
    rng = np.random.default_rng(11)
    x = rng.normal(size=shape)
    w = rng.normal(size=(3, 3, 3, shape[-1], 4))
    cotangent = rng.normal(size=(*shape[:-1], 4))
    padded = np.pad(x, ((0, 0), (1, 1), (1, 1), (1, 1), (0, 0)))

    def loss(x, w):
        return jnp.sum(blocks.winograd_conv3d_valid(x, w) * cotangent)

    padded32, w32 = jnp.asarray(padded, jnp.float32), jnp.asarray(w, jnp.float32)
    got = blocks.winograd_conv3d_valid(padded32, w32)
    got_grads = jax.grad(loss, (0, 1))(padded32, w32)
    want = _reference_conv_same(x, w)
    np.testing.assert_allclose(got, want, atol=2e-5 * np.abs(want).max())
    # the gradient of sum(conv * cotangent): wrt the padded input a correlation of the
    # cotangent with the flipped kernel, wrt the kernel the windows of the input
    grad_x = np.zeros_like(padded)
    grad_w = np.zeros_like(w)
    nx, ny, nz = shape[1:4]
    for a, b, c in np.ndindex(3, 3, 3):
        window = padded[:, a : a + nx, b : b + ny, c : c + nz]
        grad_x[:, a : a + nx, b : b + ny, c : c + nz] += cotangent @ w[a, b, c].T
        grad_w[a, b, c] = np.einsum("nxyzi,nxyzo->io", window, cotangent)
    for g, want_g in zip(got_grads, (grad_x, grad_w), strict=True):
        np.testing.assert_allclose(g, want_g, atol=2e-5 * np.abs(want_g).max())


@pytest.mark.parametrize("kernel", [1, 3, 5])
def test_blocked_kernel_convolves_2x2x2_blocks_as_the_full_grid(kernel):
    rng = np.random.default_rng(8)
    x = rng.normal(size=(2, 4, 6, 2, 3)).astype(np.float32)
    w = rng.normal(size=(kernel, kernel, kernel, 3, 2)).astype(np.float32)
    blocked = blocks.conv3d_same(blocks.space_to_depth(jnp.asarray(x)), blocks.blocked_kernel(w))
    expected = blocks.space_to_depth(jnp.asarray(_reference_conv_same(x, w), jnp.float32))
    np.testing.assert_allclose(blocked, expected, atol=1e-4)


@pytest.mark.parametrize("kernel", [2, 7])
def test_blocked_kernel_rejects_kernels_its_three_block_taps_cannot_hold(kernel):
    with pytest.raises(ValueError, match="odd kernel size <= 5"):
        blocks.blocked_kernel(jnp.zeros((kernel, kernel, kernel, 1, 1)))


@pytest.mark.parametrize("form", ["native", *blocks.CPU_FORMS])
@pytest.mark.parametrize("shape", [(2, 3, 4, 2, 2), (1, 1, 2, 1, 3), (1, 4, 4, 4, 1)])
def test_upsample_conv_equals_upsampling_then_convolving(form, shape):
    """Against NumPy on the upsampled grid: the faces' zero padding included."""
    rng = np.random.default_rng(9)
    x = rng.normal(size=shape).astype(np.float32)
    w = rng.normal(size=(3, 3, 3, shape[-1], 2)).astype(np.float32)
    fine = np.asarray(blocks.upsample_trilinear(jnp.asarray(x)))
    expected = blocks.space_to_depth(jnp.asarray(_reference_conv_same(fine, w), jnp.float32))
    got = blocks.upsample_conv3d_same(jnp.asarray(x), jnp.asarray(w), form)
    np.testing.assert_allclose(got, expected, atol=1e-4)


def test_upsample_trilinear_clamps_at_the_faces():
    """What `upsample_conv3d_same` relies on: half-pixel centres, edge values kept."""
    x = jnp.arange(3.0).reshape(1, 3, 1, 1, 1)
    up = blocks.upsample_trilinear(x)[0, :, 0, 0, 0]
    np.testing.assert_allclose(up, [0.0, 0.25, 0.75, 1.25, 1.75, 2.0])


def test_strided_conv_on_blocks_rejects_other_convolutions():
    with pytest.raises(ValueError, match="only the strided 2x2x2"):
        blocks.Conv3D(1, 1, 3, rngs=nnx.Rngs(0)).on_blocks(jnp.zeros((1, 2, 2, 2, 8)))


def test_conv_form_rejects_unknown_names():
    x, w = jnp.zeros((1, 4, 4, 4, 1)), jnp.zeros((3, 3, 3, 1, 1))
    with pytest.raises(ValueError, match="form must be one of"):
        blocks.conv3d_same(x, w, "sliced")
    with pytest.raises(ValueError, match="conv form must be one of"):
        blocks.set_conv_form(blocks.Conv3D(1, 1, 3, rngs=nnx.Rngs(0)), "fast")


@pytest.mark.parametrize("n, k", [(4, 3), (8, 5), (6, 1)])
def test_coord_conv_matches_the_convolution_of_the_coordinate_grid(n, k):
    """The closed form of the stem's coordinate channels equals convolving coord_grid, in value
    and in the kernel gradient (it is what FeatureNet adds to every sample)."""
    from nmjax.keypoints import coord_grid

    rng = np.random.default_rng(8)
    w = jnp.asarray(rng.normal(size=(k, k, k, 3, 4)), jnp.float32)
    cot = jnp.asarray(rng.normal(size=(n, n, n, 4)), jnp.float32)

    def closed(w):
        return blocks.coord_conv3d_same(w, n)

    def conv(w):
        return blocks.conv3d_same(coord_grid(n)[None], w, "native")[0]

    np.testing.assert_allclose(closed(w), conv(w), rtol=1e-5, atol=1e-5)
    g_closed = jax.grad(lambda w: jnp.sum(closed(w) * cot))(w)
    g_conv = jax.grad(lambda w: jnp.sum(conv(w) * cot))(w)
    np.testing.assert_allclose(g_closed, g_conv, rtol=1e-5, atol=1e-4)


def test_detector_value_and_gradient_do_not_depend_on_the_conv_forms():
    """The whole phase-1 loss and its gradient with XLA's 3D convolution everywhere, against the
    code's CPU choice (taps stacked for the thin stem, one 2D convolution per tap elsewhere)."""
    from nmjax import losses

    cfg = skel_preset("synth-arm", "tiny")
    model_cfg = dataclasses.replace(
        cfg.model, grid=8, channels=4, num_keypoints=4, hourglass_channels=(4, 4, 4)
    )
    rng = np.random.default_rng(6)
    voxels = jnp.asarray(rng.random((1, 3, 8, 8, 8)) > 0.7, jnp.float32)
    model = KeypointDetector(model_cfg, rngs=nnx.Rngs(0))

    def value_and_grad(form):
        blocks.set_conv_form(model, form)  # a static attribute: it lives in the graphdef
        graphdef, params = nnx.split(model)

        def loss(params):
            outputs = nnx.merge(graphdef, params)(voxels)
            return losses.skeleton_loss({"voxels": voxels, **outputs}, cfg.weights)[0]

        return jax.value_and_grad(loss)(params)

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


def test_hourglass_levels():
    assert blocks.hourglass_levels(16, 3) == 3
    assert blocks.hourglass_levels(8, 3) == 3
    assert blocks.hourglass_levels(4, 3) == 2
    assert blocks.hourglass_levels(6, 3) == 1
    assert blocks.hourglass_levels(2, 0) == 0


@pytest.fixture(scope="module", params=[4, 2], ids=["stride4", "stride2"])
def tiny_outputs(request):
    cfg = skel_preset("synth-arm", "tiny")
    cfg = dataclasses.replace(
        cfg, model=dataclasses.replace(cfg.model, heatmap_stride=request.param)
    )
    model = KeypointDetector(cfg.model, rngs=nnx.Rngs(0))
    b, t, g = cfg.data.batch_size, cfg.data.frames, cfg.model.grid
    voxels = (jax.random.uniform(jax.random.key(1), (b, t, g, g, g)) > 0.8).astype(jnp.float32)
    return cfg, model, voxels, model(voxels)


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
    recon = np.asarray(model(voxels)["recon"])
    # raw = 0 -> v_hat_t = sigmoid(10 (v_1 - 0.5)) for every frame t (Eq. 7 with tanh(0) = 0).
    v1 = np.asarray(voxels[:, :1])
    expected = 1.0 / (1.0 + np.exp(-cfg.model.decoder_sharpness * (v1 - 0.5)))
    np.testing.assert_allclose(recon, np.broadcast_to(expected, recon.shape), atol=1e-6)


def test_frames_are_independent_except_through_temporal_mean(tiny_outputs):
    _, model, voxels, out = tiny_outputs
    # Swapping two frames (t >= 1) keeps the temporal mean and frame 1: outputs swap with them.
    perm = np.arange(voxels.shape[1])
    perm[[1, 2]] = perm[[2, 1]]
    swapped = model(voxels[:, perm])
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


def _ynn_fusion_bodies(compiled_text: str) -> list[str]:
    """The fused computations a compiled CPU module hands to YNNPACK."""
    import re

    lines = [line for line in compiled_text.splitlines() if '"kind":"__ynn_fusion"' in line]
    names = [re.search(r"calls=%([\w.\-]+)", line).group(1) for line in lines]
    return [compiled_text[compiled_text.index(f"%{n} ") :].split("\n}", 1)[0] for n in names]


def test_cpu_convolutions_and_reductions_do_not_go_through_ynnpack():
    """nmjax switches YNNPACK's convolutions and reductions off (nmjax/__init__.py): its kernel
    gradients of the detector's thin convolutions were 3-4x slower than XLA's, its batch sums
    17x. Neither may land in a YNNPACK fusion of a compiled module."""
    import nmjax

    if jax.default_backend() != "cpu":
        pytest.skip("a CPU backend option")
    assert nmjax.YNN_CONVOLUTION_FLAG in os.environ["XLA_FLAGS"]
    x, w = jnp.ones((2, 16, 16, 16, 4)), jnp.ones((3, 3, 3, 4, 4))
    form = blocks.CPU_FALLBACK_FORM  # "auto" takes Winograd's form here: matmuls, no convolution
    conv = functools.partial(blocks.conv3d_same, form=form)
    grad = jax.jit(jax.grad(lambda w: jnp.sum(conv(x, w)))).lower(w).compile()
    batch_sum = jax.jit(lambda x: jnp.sum(x * 1.5, axis=0)).lower(x).compile()
    for compiled, op in ((grad, "convolution("), (batch_sum, "reduce(")):
        text = compiled.as_text()
        assert op in text
        for body in _ynn_fusion_bodies(text):
            assert op not in body, body
