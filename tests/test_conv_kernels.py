"""Tests of the convolution and GroupNorm kernels (nmjax.models.conv_kernels): every form against
NumPy or the plain XLA form beside it, in value and gradient, and the choice of form.

The explicit forms run on every backend. The tests of what "auto" takes on CPU (and of the CPU
compiler's options) skip elsewhere, where "auto" is XLA's native convolution.
"""

from __future__ import annotations

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from nmjax.keypoints import coord_grid
from nmjax.models import blocks
from nmjax.models import conv_kernels as ck
from nmjax.models.conv_kernels import Evaluation

cpu_only = pytest.mark.skipif(
    jax.default_backend() != "cpu",
    reason="checks the forms 'auto' takes on CPU; on this backend 'auto' is XLA's native "
    "convolution (the explicit forms are tested on every backend)",
)


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


# --- the choice of form -------------------------------------------------------------------------


def test_resolve_takes_the_native_convolution_off_cpu_and_the_cpu_forms_on_cpu():
    f32, bf16 = jnp.float32, jnp.bfloat16
    for backend in ("gpu", "tpu"):
        assert ck.resolve("auto", backend, (32, 32, 32), 3, f32) == "native"
    assert ck.resolve("auto", "cpu", (8, 9, 8), 3, f32) == "winograd"
    assert ck.resolve("auto", "cpu", (8, 4, 8), 3, f32) == "stacked"  # a side under the minimum
    assert ck.resolve("auto", "cpu", (16, 16, 16), 5, f32) == "stacked"
    assert ck.resolve("auto", "cpu", (16, 16, 16), 3, bf16) == "stacked"
    # A named form on every backend; Winograd's only where it applies, at any grid.
    for backend in ("cpu", "gpu"):
        for form in ("native", "per_tap", "stacked"):
            assert ck.resolve(form, backend, (2, 2, 2), 5, f32) == form
        assert ck.resolve("winograd", backend, (2, 2, 2), 3, f32) == "winograd"
        assert ck.resolve("winograd", backend, (16, 16, 16), 5, f32) == "stacked"
        assert ck.resolve("winograd", backend, (16, 16, 16), 3, bf16) == "stacked"
    assert ck.resolve("auto", None, (8, 8, 8), 3, f32) == (
        "winograd" if jax.default_backend() == "cpu" else "native"
    )


def test_unknown_forms_and_dtypes_are_refused_naming_the_config_field():
    x, w = jnp.zeros((1, 4, 4, 4, 1)), jnp.zeros((3, 3, 3, 1, 1))
    with pytest.raises(ValueError, match="form must be one of"):
        ck.conv3d_same(x, w, "sliced")
    with pytest.raises(ValueError, match="model.conv_form must be one of"):
        Evaluation("fast")
    with pytest.raises(ValueError, match="model.conv_form must be one of"):
        ck.resolve("fast", "cpu", (4, 4, 4), 3, jnp.float32)
    with pytest.raises(ValueError, match="model.compute_dtype must be one of"):
        Evaluation("auto", "float16")
    with pytest.raises(ValueError, match="op must be one of"):
        ck.conv3d(x, w, "dilated")


# --- every op against its plain XLA form ---------------------------------------------------------

# (op, input shape, kernel size); the forms matter where a stride-1 'SAME' convolution is inside.
FORM_OPS = [
    ("same", (2, 5, 4, 6, 2), 3),
    ("same", (2, 5, 4, 6, 2), 5),
    ("upsampled", (2, 3, 2, 4, 2), 3),
    ("upsampled", (1, 2, 2, 2, 2), 5),
    ("coords", (2, 6, 6, 6, 1), 5),
    ("coords", (1, 5, 5, 5, 2), 3),
]
FIXED_OPS = [
    ("same", (2, 3, 4, 2, 2), 1),
    ("strided", (2, 4, 6, 2, 2), 2),
    ("transposed", (2, 3, 2, 1, 2), 2),
]


@pytest.mark.parametrize(
    ("op", "shape", "k", "form"),
    [(*case, form) for case in FORM_OPS for form in ck.CONV_FORMS]
    + [(*case, "auto") for case in FIXED_OPS],
)
def test_every_op_in_every_form_equals_its_native_form_in_value_and_gradient(op, shape, k, form):
    """The layer's kernel (`conv3d`) against `conv3d_native`: the thin inputs, odd sides (no
    blocked stem), kernels Winograd's form does not take, both the fused and the written-out
    upsampling; the pointwise, strided and transposed convolutions take no form."""
    rng = np.random.default_rng(3)
    ci = shape[-1] + 3 if op == "coords" else shape[-1]
    x = jnp.asarray(rng.normal(size=shape), jnp.float32)
    w = jnp.asarray(rng.normal(size=(k, k, k, ci, 3)), jnp.float32)
    evaluation = Evaluation(form)
    y = ck.conv3d_native(x, w, op)
    cotangent = jnp.asarray(rng.normal(size=y.shape), jnp.float32)

    def grads(fn):  # compiled as one program: op by op, Winograd's many small steps are slow
        return jax.jit(jax.grad(lambda x, w: jnp.sum(fn(x, w) * cotangent), argnums=(0, 1)))(x, w)

    got = jax.jit(ck.conv3d, static_argnums=(2, 3))(x, w, op, evaluation)
    assert got.shape == y.shape and got.dtype == jnp.float32
    scale = float(jnp.max(jnp.abs(y)))
    np.testing.assert_allclose(got, y, atol=2e-5 * scale, err_msg=f"{op} {form}")
    want_grads = grads(lambda x, w: ck.conv3d_native(x, w, op))
    got_grads = grads(lambda x, w: ck.conv3d(x, w, op, evaluation))
    for g, want in zip(got_grads, want_grads, strict=True):
        np.testing.assert_allclose(g, want, atol=2e-5 * float(jnp.max(jnp.abs(want))))


def test_native_strided_and_transposed_convolutions_match_their_definitions():
    """The plain forms themselves: every output cell of the stride-2 convolution sees its own
    2x2x2 block, every input cell of the transposed one paints its own block."""
    rng = np.random.default_rng(2)
    x = rng.normal(size=(1, 4, 2, 2, 3)).astype(np.float32)
    w = rng.normal(size=(2, 2, 2, 3, 5)).astype(np.float32)
    pooled = np.asarray(ck.conv3d_native(jnp.asarray(x), jnp.asarray(w), "strided"))
    painted = np.asarray(ck.conv3d_native(jnp.asarray(x), jnp.asarray(w), "transposed"))
    for i, j, k in np.ndindex(2, 1, 1):
        block = x[0, 2 * i : 2 * i + 2, 2 * j : 2 * j + 2, 2 * k : 2 * k + 2]
        np.testing.assert_allclose(
            pooled[0, i, j, k], np.einsum("abci,abcio->o", block, w), rtol=1e-5
        )
    for i, j, k in np.ndindex(4, 2, 2):
        np.testing.assert_allclose(
            painted[0, 2 * i : 2 * i + 2, 2 * j : 2 * j + 2, 2 * k : 2 * k + 2],
            np.einsum("i,abcio->abco", x[0, i, j, k], w),
            rtol=1e-5,
            atol=1e-6,
        )


def test_compute_dtype_casts_the_convolution_and_returns_float32():
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.normal(size=(2, 8, 8, 8, 3)), jnp.float32)
    w = jnp.asarray(rng.normal(size=(3, 3, 3, 3, 4)), jnp.float32)
    ref = ck.conv3d(x, w)
    bf16 = Evaluation("auto", "bfloat16")
    out = ck.conv3d(x, w, "same", bf16)
    assert out.dtype == jnp.float32
    assert "bf16" in _jaxpr(lambda x, w: ck.conv3d(x, w, "same", bf16), x, w)
    np.testing.assert_allclose(out, ref, atol=0.05 * float(jnp.max(jnp.abs(ref))))


# --- stride-1 'SAME' forms ----------------------------------------------------------------------


# Each (kernel, form) a distinct computation: a 1x1x1 kernel is one matmul in every form, and a
# named form `resolve` replaces (winograd for k=5 takes stacked) would repeat another case.
SAME_CASES = [(1, "native")] + [
    (kernel, form)
    for kernel in (3, 5)
    for form in ("native", *ck.CPU_FORMS)
    if ck.resolve(form, "cpu", (6, 5, 4), kernel, jnp.float32) == form
]


@pytest.mark.parametrize(("kernel", "form"), SAME_CASES)
def test_conv3d_same_matches_numpy(kernel, form):
    conv = blocks.Conv3D(2, 3, kernel, evaluation=Evaluation(form), rngs=nnx.Rngs(0))
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
        return jnp.sum(ck.conv3d_same(x, w, form) * cotangent)

    results = {}
    winograd_convs = 0 if kernel == 3 else 1  # k=5 falls back to the stacked form
    for form, convs in (
        ("native", 1),
        ("per_tap", kernel),
        ("stacked", 1),
        ("winograd", winograd_convs),
    ):
        conv = functools.partial(ck.conv3d_same, form=form)
        assert _conv_count(conv, x, w) == convs, form
        grads = jax.jit(jax.grad(loss, argnums=(0, 1)), static_argnums=2)(x, w, form)
        results[form] = (jax.jit(conv)(x, w), *grads)
    for form in ck.CPU_FORMS:
        for got, want in zip(results[form], results["native"], strict=True):
            if form == "winograd" and kernel == 3:  # about 1e-5 of the largest value
                atol = 2e-5 * float(jnp.max(jnp.abs(want)))
                np.testing.assert_allclose(got, want, atol=atol, err_msg=form)
            else:
                np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-4, err_msg=form)


@cpu_only
def test_conv3d_same_stacks_the_taps_into_one_2d_convolution_on_cpu():
    """Where "auto" does not take Winograd's form on CPU (grids under WINOGRAD_MIN_SIDE, k=5,
    bfloat16), one 2D convolution with the k taps stacked, never XLA's 3D convolution."""
    rng = np.random.default_rng(5)
    side = ck.WINOGRAD_MIN_SIDE
    cases = [(3, 1, 4, jnp.float32, 4), (3, 16, 64, jnp.float32, 4), (3, 128, 128, jnp.float32, 4)]
    cases += [(5, 1, 4, jnp.float32, side), (3, 8, 8, jnp.bfloat16, side)]
    for k, ci, co, dtype, n in cases:  # the stem, a coarse decoder conv, the paper's widths
        x = jnp.zeros((1, n, n, n, ci), dtype)
        w = jnp.asarray(rng.normal(size=(k, k, k, ci, co)), dtype)
        jaxpr = _jaxpr(ck.conv3d_same, x, w)
        assert jaxpr.count("conv_general_dilated") == 1, ci  # not one per tap
        assert jaxpr.count("window_strides=(1, 1)") == 1, ci  # 2D, never XLA's 3D on CPU
        assert f"{k},{k},{k * ci},{co}]" in jaxpr.replace(" ", ""), ci  # the k-deep kernel


@cpu_only
def test_conv3d_same_takes_winograds_form_on_cpu_for_float32_3x3x3_on_large_grids():
    side = ck.WINOGRAD_MIN_SIDE
    x = jnp.zeros((2, side, side + 2, side, 16), jnp.float32)
    w = jnp.zeros((3, 3, 3, 16, 32), jnp.float32)
    jaxpr = _jaxpr(ck.conv3d_same, x, w)
    assert "conv_general_dilated" not in jaxpr
    # 216 tile positions, each one matmul over B * tiles = 2 * 2 * 3 * 2 rows
    assert "f32[216,24,32]" in jaxpr.replace(" ", "")
    assert _conv_count(ck.conv3d_same, x[:, :, :4], w) == 1  # a side under the minimum


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
        return jnp.sum(ck.winograd_conv3d_valid(x, w) * cotangent)

    padded32, w32 = jnp.asarray(padded, jnp.float32), jnp.asarray(w, jnp.float32)
    got = jax.jit(ck.winograd_conv3d_valid)(padded32, w32)
    got_grads = jax.jit(jax.grad(loss, (0, 1)))(padded32, w32)
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


# --- the full-grid rewrites ---------------------------------------------------------------------


@pytest.mark.parametrize("kernel", [1, 3, 5])
def test_blocked_kernel_convolves_2x2x2_blocks_as_the_full_grid(kernel):
    rng = np.random.default_rng(8)
    x = rng.normal(size=(2, 4, 6, 2, 3)).astype(np.float32)
    w = rng.normal(size=(kernel, kernel, kernel, 3, 2)).astype(np.float32)
    blocked = ck.conv3d_same(ck.space_to_depth(jnp.asarray(x)), ck.blocked_kernel(w))
    expected = ck.space_to_depth(jnp.asarray(_reference_conv_same(x, w), jnp.float32))
    np.testing.assert_allclose(blocked, expected, atol=1e-4)


@pytest.mark.parametrize("kernel", [2, 7])
def test_blocked_kernel_rejects_kernels_its_three_block_taps_cannot_hold(kernel):
    with pytest.raises(ValueError, match="odd kernel size <= 5"):
        ck.blocked_kernel(jnp.zeros((kernel, kernel, kernel, 1, 1)))


@pytest.mark.parametrize("form", ["native", *ck.CPU_FORMS])
@pytest.mark.parametrize("shape", [(2, 3, 4, 2, 2), (1, 1, 2, 1, 3), (1, 4, 4, 4, 1)])
def test_upsample_conv_equals_upsampling_then_convolving(form, shape):
    """Against NumPy on the upsampled grid: the faces' zero padding included."""
    rng = np.random.default_rng(9)
    x = rng.normal(size=shape).astype(np.float32)
    w = rng.normal(size=(3, 3, 3, shape[-1], 2)).astype(np.float32)
    fine = np.asarray(ck.upsample_trilinear(jnp.asarray(x)))
    expected = ck.space_to_depth(jnp.asarray(_reference_conv_same(fine, w), jnp.float32))
    got = jax.jit(ck.upsample_conv3d_blocks, static_argnums=2)(jnp.asarray(x), jnp.asarray(w), form)
    np.testing.assert_allclose(got, expected, atol=1e-4)


def test_upsample_trilinear_clamps_at_the_faces():
    """What `upsample_conv3d_blocks` relies on: half-pixel centres, edge values kept."""
    x = jnp.arange(3.0).reshape(1, 3, 1, 1, 1)
    up = ck.upsample_trilinear(x)[0, :, 0, 0, 0]
    np.testing.assert_allclose(up, [0.0, 0.25, 0.75, 1.25, 1.75, 2.0])


@pytest.mark.parametrize("n, k", [(4, 3), (8, 5), (6, 1)])
def test_coord_conv_matches_the_convolution_of_the_coordinate_grid(n, k):
    """The closed form of the stem's coordinate channels equals convolving coord_grid, in value
    and in the kernel gradient (it is what the CoordConv adds to every sample)."""
    rng = np.random.default_rng(8)
    w = jnp.asarray(rng.normal(size=(k, k, k, 3, 4)), jnp.float32)
    cot = jnp.asarray(rng.normal(size=(n, n, n, 4)), jnp.float32)

    def closed(w):
        return ck.coord_channels_conv3d(w, n)

    def conv(w):
        return ck.conv3d_same(coord_grid(n)[None], w, "native")[0]

    np.testing.assert_allclose(closed(w), conv(w), rtol=1e-5, atol=1e-5)
    g_closed = jax.grad(lambda w: jnp.sum(closed(w) * cot))(w)
    g_conv = jax.grad(lambda w: jnp.sum(conv(w) * cot))(w)
    np.testing.assert_allclose(g_closed, g_conv, rtol=1e-5, atol=1e-4)


def test_coord_conv_refuses_inputs_that_do_not_leave_room_for_the_coordinates():
    with pytest.raises(ValueError, match="Ci - 3"):
        ck.coord_conv3d(jnp.zeros((1, 4, 4, 4, 2)), jnp.zeros((3, 3, 3, 4, 1)))
    with pytest.raises(ValueError, match="Ci - 3"):
        ck.coord_conv3d(jnp.zeros((1, 4, 4, 2, 1)), jnp.zeros((3, 3, 3, 4, 1)))


# --- GroupNorm ----------------------------------------------------------------------------------


@pytest.mark.parametrize(("shape", "groups"), [((2, 4, 6, 2, 32), 2), ((1, 128, 8), 4)])
def test_group_norm_equals_its_native_form_in_value_and_gradient(shape, groups):
    rng = np.random.default_rng(1)
    channels = shape[-1]
    x = jnp.asarray(1.5 * rng.normal(size=shape) + 0.7, jnp.float32)
    scale, bias = (jnp.asarray(rng.normal(size=channels), jnp.float32) for _ in range(2))
    cotangent = jnp.asarray(rng.normal(size=shape), jnp.float32)
    fast = functools.partial(ck.group_norm, groups=groups, eps=1e-5)
    plain = functools.partial(ck.group_norm_native, groups=groups, eps=1e-5)

    @functools.partial(jax.jit, static_argnums=0)  # one program, not op by op
    def value_and_grads(fn):
        return fn(x, scale, bias), jax.grad(
            lambda *a: jnp.sum(fn(*a) * cotangent), argnums=(0, 1, 2)
        )(x, scale, bias)

    (y, grads), (want_y, want_grads) = value_and_grads(fast), value_and_grads(plain)
    np.testing.assert_allclose(y, want_y, rtol=1e-5, atol=1e-5)
    for g, want in zip(grads, want_grads, strict=True):
        np.testing.assert_allclose(g, want, atol=1e-4 * float(jnp.max(jnp.abs(want))))


# --- the CPU compiler ---------------------------------------------------------------------------


def _ynn_fusion_bodies(compiled_text: str) -> list[str]:
    """The fused computations a compiled CPU module hands to YNNPACK."""
    import re

    lines = [line for line in compiled_text.splitlines() if '"kind":"__ynn_fusion"' in line]
    names = [re.search(r"calls=%([\w.\-]+)", line).group(1) for line in lines]
    return [compiled_text[compiled_text.index(f"%{n} ") :].split("\n}", 1)[0] for n in names]


@pytest.mark.skipif(
    jax.default_backend() != "cpu",
    reason="YNNPACK is an option of XLA's CPU backend; nmjax sets no flag for others",
)
def test_cpu_convolutions_and_reductions_do_not_go_through_ynnpack():
    """nmjax switches YNNPACK's convolutions and reductions off (nmjax/__init__.py): its kernel
    gradients of the detector's thin convolutions were 3-4x slower than XLA's, its batch sums
    17x. Neither may land in a YNNPACK fusion of a compiled module."""
    import nmjax

    assert nmjax.YNN_CONVOLUTION_FLAG in os.environ["XLA_FLAGS"]
    x, w = jnp.ones((2, 16, 16, 16, 4)), jnp.ones((3, 3, 3, 4, 4))
    form = ck.CPU_FALLBACK_FORM  # "auto" takes Winograd's form here: matmuls, no convolution
    conv = functools.partial(ck.conv3d_same, form=form)
    grad = jax.jit(jax.grad(lambda w: jnp.sum(conv(x, w)))).lower(w).compile()
    batch_sum = jax.jit(lambda x: jnp.sum(x * 1.5, axis=0)).lower(x).compile()
    for compiled, op in ((grad, "convolution("), (batch_sum, "reduce(")):
        text = compiled.as_text()
        assert op in text
        for body in _ynn_fusion_bodies(text):
            assert op not in body, body
