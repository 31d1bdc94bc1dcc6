"""The 3D layers of the keypoint detector (paper Fig. 9, docs/architecture.md §6), channels-last
(..., X, Y, Z, C), as the authors released them.

Every layer takes a batch (B, X, Y, Z, C); callers fold time into the batch axis. A layer says
what it computes; how a convolution or a GroupNorm is evaluated fast on a backend is
`nmjax.models.conv_kernels`' business: each layer calls one kernel function there, in the form
and compute dtype of the `Evaluation` it was built with (config fields model.conv_form and
model.compute_dtype).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from nmjax.models import conv_kernels
from nmjax.models.conv_kernels import Evaluation, group_norm

# LeakyReLU negative slope: PyTorch's default, which the released network uses everywhere.
LEAK = 0.01
# GroupNorm epsilon: PyTorch's default, as released (flax's default is 1e-6).
GN_EPS = 1e-5
# Initial weight scales of the released network (its `weights_init`): every convolution N(0,
# 0.02); those inside the feature nets' conv blocks (stem, pools, residual blocks, hourglass,
# upsamplings) N(0, 0.001). Biases start at 0, GroupNorm at scale 1, bias 0. A conv followed by
# GroupNorm computes the same function at any weight scale, but Adam moves each weight by about
# the learning rate per step, so the scale sets how fast those layers change.
INIT_STD = 0.02
FEATURE_INIT_STD = 0.001
# G / g: f_feat pools twice (4) or once (2) before the hourglass; f_dec upsamples as often.
HEATMAP_STRIDES = (2, 4)
# The convolutions of a model built without a configuration: "auto" form, float32.
DEFAULT_EVALUATION = Evaluation()


def num_groups(channels: int) -> int:
    """GroupNorm groups: channels / 16 (docs/architecture.md §6), at least 1 and dividing
    `channels`."""
    return math.gcd(channels, max(1, channels // 16))


def check_heatmap_stride(stride: int) -> None:
    """Raises ValueError unless `stride` is one of HEATMAP_STRIDES (field model.heatmap_stride)."""
    if stride not in HEATMAP_STRIDES:
        raise ValueError(f"model.heatmap_stride must be one of {HEATMAP_STRIDES}, got {stride}")


def normal_init(key: jax.Array, shape: tuple[int, ...], std: float) -> jax.Array:
    """N(0, std^2) weights of `shape`, drawn with NumPy from a seed taken from `key`.

    jax.random would compile one sampler per distinct weight shape, which dominated model
    construction time on CPU.
    """
    seed = np.asarray(jax.random.key_data(key)).ravel().tolist()
    return jnp.asarray(np.random.default_rng(seed).normal(0.0, std, shape), jnp.float32)


class GroupNorm(nnx.GroupNorm):
    """`flax.nnx.GroupNorm` (same parameters, same function: statistics over every axis but the
    first and the last), evaluated by `conv_kernels.group_norm`."""

    def __call__(self, x: jax.Array, *, mask: jax.Array | None = None) -> jax.Array:
        if (
            mask is not None
            or self.reduction_axes is not None
            or not (self.use_scale and self.use_bias)
        ):
            raise ValueError(
                "nmjax GroupNorm: no mask or reduction_axes, scale and bias on (flax.nnx.GroupNorm "
                "takes the other settings)"
            )
        return group_norm(x, self.scale[...], self.bias[...], self.num_groups, self.epsilon)


def group_norm_layer(channels: int, rngs: nnx.Rngs) -> GroupNorm:
    """The detector's GroupNorm: channels / 16 groups, epsilon `GN_EPS`, scale 1, bias 0."""
    return GroupNorm(channels, num_groups=num_groups(channels), epsilon=GN_EPS, rngs=rngs)


class Conv3D(nnx.Module):
    """3D convolution, channels-last, 'SAME' padding, kernel (k, k, k, in, out) and bias.

    kernel=k, stride=1: ordinary convolution (odd k). kernel=2, stride=2: strided convolution
    halving each axis ("pool"). transpose=True, kernel=2, stride=2: transposed convolution
    doubling each axis. upsample=True: the input is first upsampled 2x by trilinear
    interpolation (`conv_kernels.upsample_trilinear`), then convolved (f_dec). coords=True:
    CoordConv, the 3 coordinate channels of the grid (docs/architecture.md §4) appended to the
    input's channels, so the input has in - 3 of them (the stem). Kernel initialised N(0,
    init_std^2) (`INIT_STD`, the released network's), bias 0. `conv_kernels.conv3d` evaluates the
    convolution in the form and compute dtype of `evaluation`; the result is float32.
    """

    def __init__(
        self,
        in_ch: int,
        out_ch: int,
        kernel: int = 3,
        stride: int = 1,
        *,
        transpose: bool = False,
        upsample: bool = False,
        coords: bool = False,
        init_std: float = INIT_STD,
        evaluation: Evaluation = DEFAULT_EVALUATION,
        rngs: nnx.Rngs,
    ):
        if stride not in (1, kernel) or (stride == kernel and kernel not in (1, 2)):
            raise ValueError(
                f"Conv3D supports stride 1, or kernel = stride = 2; got {kernel}, {stride}"
            )
        if transpose and (kernel, stride) != (2, 2):
            raise ValueError("Conv3D: transposed convolution only with kernel = stride = 2")
        if (upsample or coords) and (stride != 1 or kernel % 2 == 0 or upsample == coords):
            raise ValueError(
                "Conv3D: upsample or coords (one of them) only with stride 1 and an odd kernel"
            )
        if transpose:
            self.op = "transposed"
        elif stride == 2:
            self.op = "strided"
        else:
            self.op = "upsampled" if upsample else "coords" if coords else "same"
        self.evaluation = evaluation
        shape = (kernel, kernel, kernel, in_ch, out_ch)
        self.kernel = nnx.Param(normal_init(rngs.params(), shape, init_std))
        self.bias = nnx.Param(jnp.zeros((out_ch,), jnp.float32))

    def __call__(self, x: jax.Array) -> jax.Array:
        return conv_kernels.conv3d(x, self.kernel[...], self.op, self.evaluation) + self.bias[...]


class ConvNormAct(nnx.Module):
    """conv (kernel k, stride s, SAME padding; upsampling or CoordConv as `Conv3D` takes them)
    -> GroupNorm -> LeakyReLU."""

    def __init__(
        self,
        in_ch: int,
        out_ch: int,
        kernel: int = 3,
        stride: int = 1,
        *,
        upsample: bool = False,
        coords: bool = False,
        init_std: float = INIT_STD,
        evaluation: Evaluation = DEFAULT_EVALUATION,
        rngs: nnx.Rngs,
    ):
        self.conv = Conv3D(
            in_ch,
            out_ch,
            kernel,
            stride,
            upsample=upsample,
            coords=coords,
            init_std=init_std,
            evaluation=evaluation,
            rngs=rngs,
        )
        self.norm = group_norm_layer(out_ch, rngs)

    def __call__(self, x: jax.Array) -> jax.Array:
        return nnx.leaky_relu(self.norm(self.conv(x)), LEAK)


class ResBlock(nnx.Module):
    """Residual block as released: conv3-GN-LeakyReLU-conv3-GN on one branch, the identity or a
    1x1x1 projection + GroupNorm (when widths differ) on the skip, and branch + skip returned
    with no activation after the sum (the release's `leaky_relu(res + skip, True)` passes True as
    the negative slope: the identity). The output can be negative."""

    def __init__(
        self,
        in_ch: int,
        out_ch: int,
        *,
        init_std: float = FEATURE_INIT_STD,
        evaluation: Evaluation = DEFAULT_EVALUATION,
        rngs: nnx.Rngs,
    ):
        kw = {"init_std": init_std, "evaluation": evaluation, "rngs": rngs}
        self.conv1 = ConvNormAct(in_ch, out_ch, 3, **kw)
        self.conv2 = Conv3D(out_ch, out_ch, 3, **kw)
        self.norm2 = group_norm_layer(out_ch, rngs)
        self.skip = SkipProjection(in_ch, out_ch, **kw) if in_ch != out_ch else None

    def __call__(self, x: jax.Array) -> jax.Array:
        y = self.norm2(self.conv2(self.conv1(x)))
        return y + (x if self.skip is None else self.skip(x))


class SkipProjection(nnx.Module):
    """The skip of a residual block that changes width: 1x1x1 conv, then GroupNorm."""

    def __init__(
        self,
        in_ch: int,
        out_ch: int,
        *,
        init_std: float,
        evaluation: Evaluation = DEFAULT_EVALUATION,
        rngs: nnx.Rngs,
    ):
        self.conv = Conv3D(in_ch, out_ch, 1, init_std=init_std, evaluation=evaluation, rngs=rngs)
        self.norm = group_norm_layer(out_ch, rngs)

    def __call__(self, x: jax.Array) -> jax.Array:
        return self.norm(self.conv(x))


class Pool(nnx.Module):
    """Strided 2x2x2 convolution halving each spatial axis, then GroupNorm + LeakyReLU."""

    def __init__(
        self,
        in_ch: int,
        out_ch: int,
        *,
        init_std: float = FEATURE_INIT_STD,
        evaluation: Evaluation = DEFAULT_EVALUATION,
        rngs: nnx.Rngs,
    ):
        self.block = ConvNormAct(
            in_ch, out_ch, 2, 2, init_std=init_std, evaluation=evaluation, rngs=rngs
        )

    def __call__(self, x: jax.Array) -> jax.Array:
        return self.block(x)


class Upsample(nnx.Module):
    """Transposed 2x2x2 convolution doubling each spatial axis, then GroupNorm + LeakyReLU."""

    def __init__(
        self,
        in_ch: int,
        out_ch: int,
        *,
        init_std: float = FEATURE_INIT_STD,
        evaluation: Evaluation = DEFAULT_EVALUATION,
        rngs: nnx.Rngs,
    ):
        self.conv = Conv3D(
            in_ch, out_ch, 2, 2, transpose=True, init_std=init_std, evaluation=evaluation, rngs=rngs
        )
        self.norm = group_norm_layer(out_ch, rngs)

    def __call__(self, x: jax.Array) -> jax.Array:
        return nnx.leaky_relu(self.norm(self.conv(x)), LEAK)


def hourglass_levels(size: int, requested: int) -> int:
    """How many pool levels an hourglass on a `size`^3 grid can have: at most `requested`, and no
    more than the number of times `size` halves to an integer (a G=16 input has g=4: 2 levels)."""
    levels = 0
    while levels < requested and size % 2 == 0 and size > 1:
        size //= 2
        levels += 1
    return levels


class Hourglass(nnx.Module):
    """3D hourglass (Xu et al. 2019b style, paper Fig. 9) as released: pool/residual levels down;
    on the way up a residual block before every transposed-conv upsampling, and the residual skip
    of each resolution added after it.

    With widths (32, 48, 72) and input width c: c@g -> 32@g/2 -> 48@g/4 -> 72@g/8, then
    res(72), up -> 48, + skip, res(48), up -> 32, + skip, res(32), up -> c, + skip.
    """

    def __init__(
        self,
        channels: int,
        widths: tuple[int, ...],
        size: int,
        *,
        evaluation: Evaluation = DEFAULT_EVALUATION,
        rngs: nnx.Rngs,
    ):
        levels = hourglass_levels(size, len(widths))
        widths = (channels, *widths[:levels])
        kw = {"evaluation": evaluation, "rngs": rngs}
        self.down = nnx.List([_Down(widths[i], widths[i + 1], **kw) for i in range(levels)])
        self.skips = nnx.List([ResBlock(w, w, **kw) for w in widths[:levels]])
        # up_res[j] runs before up[j]: widths 72, 48, 32 for the paper's hourglass.
        self.up_res = nnx.List(
            [ResBlock(widths[i + 1], widths[i + 1], **kw) for i in reversed(range(levels))]
        )
        self.up = nnx.List(
            [Upsample(widths[i + 1], widths[i], **kw) for i in reversed(range(levels))]
        )

    def __call__(self, x: jax.Array) -> jax.Array:
        skips = []
        for down, skip in zip(self.down, self.skips, strict=True):  # fixed depth, not data
            skips.append(skip(x))
            x = down(x)
        for res, up, skip in zip(self.up_res, self.up, reversed(skips), strict=True):
            x = up(res(x)) + skip
        return x


class _Down(nnx.Module):
    """One hourglass level down: strided pool then a residual block changing the width."""

    def __init__(self, in_ch: int, out_ch: int, *, evaluation: Evaluation, rngs: nnx.Rngs):
        self.pool = Pool(in_ch, in_ch, evaluation=evaluation, rngs=rngs)
        self.res = ResBlock(in_ch, out_ch, evaluation=evaluation, rngs=rngs)

    def __call__(self, x: jax.Array) -> jax.Array:
        return self.res(self.pool(x))


class FeatureNet(nnx.Module):
    """f_feat of paper Fig. 9: (B, G, G, G) occupancy -> (B, g, g, g, C) features, g = G / stride.

    CoordConv conv5 on [occupancy, x, y, z] (-> C/4) + GN + LeakyReLU, pool, residual
    (C/4 -> C/2), pool (stride 4 only), hourglass at g, residual (C/2 -> C).
    """

    def __init__(
        self,
        channels: int,
        hourglass_channels: tuple[int, ...],
        grid: int,
        stride: int = 4,
        *,
        evaluation: Evaluation = DEFAULT_EVALUATION,
        rngs: nnx.Rngs,
    ):
        check_heatmap_stride(stride)
        c4, c2 = max(1, channels // 4), max(1, channels // 2)
        kw = {"evaluation": evaluation, "rngs": rngs}
        self.stem = ConvNormAct(1 + 3, c4, 5, coords=True, init_std=FEATURE_INIT_STD, **kw)
        self.pool1 = Pool(c4, c4, **kw)
        self.res1 = ResBlock(c4, c2, **kw)
        self.pool2 = Pool(c2, c2, **kw) if stride == 4 else None
        self.hourglass = Hourglass(c2, hourglass_channels, grid // stride, **kw)
        self.res2 = ResBlock(c2, channels, **kw)

    def __call__(self, voxels: jax.Array) -> jax.Array:
        x = self.res1(self.pool1(self.stem(voxels[..., None])))
        if self.pool2 is not None:
            x = self.pool2(x)
        return self.res2(self.hourglass(x))
