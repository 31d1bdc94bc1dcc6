"""3D convolution blocks of the keypoint detector (paper Fig. 9): channels-last (..., X, Y, Z, C).

Every block takes a batch (B, X, Y, Z, C); callers fold time into the batch axis.

`Conv3D` computes exactly the 3D convolution but, on CPU and for inputs of few channels, not with
XLA's 3D convolution, which is 3-10x slower there than its 2D convolution: a stride-1 kernel is
evaluated as 2D convolutions over (y, z) with x folded into the batch (`conv3d_same`); the strided
2x2x2 "pool" is a space-to-depth reshape and a matmul, the 2x2x2 transposed convolution a matmul
and a depth-to-space reshape. On GPU/TPU backends the native convolution is used.

`Conv3D.compute_dtype` ("float32" or "bfloat16", set for a whole model by `set_compute_dtype`)
is the precision of the convolution itself: input and kernel are cast to it and the result cast
back to float32, so parameters, normalisation and everything downstream stay float32.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from nmjax.keypoints import coord_grid

LEAK = 0.2  # LeakyReLU slope


def num_groups(channels: int) -> int:
    """GroupNorm groups: channels / 16 (DESIGN section 6), at least 1 and dividing `channels`."""
    return math.gcd(channels, max(1, channels // 16))


_NDHWC = ("NDHWC", "DHWIO", "NDHWC")
# Inputs smaller than this (elements) use XLA's 3D convolution: fast enough there, and it
# compiles to fewer operations.
SLICED_CONV_MIN_SIZE = 1 << 18
# ... and so do inputs of at least this many channels. The sliced form holds one copy of its input
# per depth tap for the kernel gradient, and its backward pass makes as many input gradients and
# transposed copies: at the paper's widths that doubled the phase-1 step's temporaries (39 GiB
# against 18.5 GiB at B=3, T=10, G=64, C=128, K=28), and there XLA's CPU 3D convolution is as
# fast (1.7x faster at 64 channels on 64^3; docs/performance.md, "Memory at paper scale").
SLICED_CONV_MAX_CHANNELS = 32
# Thin inputs (k * channels up to this) stack their k depth taps on the channel axis: one 2D
# convolution with a k-times deeper kernel, one weight gradient instead of k (the FeatureNet stem
# at G=64 kept five 1 GiB transposed gradients alive), and 1.3-1.9x faster on CPU than one 2D
# convolution per tap at the cpu preset's 1-4 channels; at 8-16 channels it is slower.
STACKED_TAPS_MAX_CHANNELS = 15
_NHWC = ("NHWC", "HWIO", "NHWC")
COMPUTE_DTYPES = ("float32", "bfloat16")
# G / g: f_feat pools twice (4) or once (2) before the hourglass; f_dec upsamples as often.
HEATMAP_STRIDES = (2, 4)


def check_heatmap_stride(stride: int) -> None:
    """Raises ValueError unless `stride` is one of HEATMAP_STRIDES (field model.heatmap_stride)."""
    if stride not in HEATMAP_STRIDES:
        raise ValueError(f"model.heatmap_stride must be one of {HEATMAP_STRIDES}, got {stride}")


def check_compute_dtype(name: str) -> None:
    """Raises ValueError unless `name` is one of COMPUTE_DTYPES (field model.compute_dtype)."""
    if name not in COMPUTE_DTYPES:
        raise ValueError(
            f"model.compute_dtype must be one of {', '.join(COMPUTE_DTYPES)}, got {name!r}"
        )


def in_compute_dtype(name: str, *arrays: jax.Array) -> tuple[jax.Array, ...]:
    """`arrays` cast to the compute dtype `name` ("float32" leaves them as they are)."""
    if name == "float32":
        return arrays
    return tuple(a.astype(jnp.dtype(name)) for a in arrays)


def conv3d_same(x: jax.Array, kernel: jax.Array) -> jax.Array:
    """Stride-1 'SAME' 3D convolution (cross-correlation) of x (B,X,Y,Z,Ci) with (k,k,k,Ci,Co).

    Odd k only. On CPU, for inputs of at least `SLICED_CONV_MIN_SIZE` elements and fewer than
    `SLICED_CONV_MAX_CHANNELS` channels, 2D convolutions over (Y, Z) with X folded into the batch
    axis, one per offset a along X of the shifted planes x[:, a : a + X] (a fixed loop over kernel
    taps, not over data), summed; with k * Ci <= `STACKED_TAPS_MAX_CHANNELS` the k shifted planes
    are concatenated on the channel axis into a single 2D convolution instead. Otherwise XLA's
    native 3D convolution.
    """
    k = kernel.shape[0]
    if k % 2 == 0:
        raise ValueError(f"conv3d_same needs an odd kernel size, got {k}")
    b, nx, ny, nz, ci = x.shape
    native = jax.default_backend() != "cpu" or x.size < SLICED_CONV_MIN_SIZE
    if native or ci >= SLICED_CONV_MAX_CHANNELS:
        return jax.lax.conv_general_dilated(x, kernel, (1, 1, 1), "SAME", dimension_numbers=_NDHWC)
    p = k // 2
    padded = jnp.pad(x, ((0, 0), (p, p), (p, p), (p, p), (0, 0)))
    planes = [padded[:, a : a + nx] for a in range(k)]  # (B, X, Y + 2p, Z + 2p, Ci) each
    kernels = list(kernel)  # (k, k, Ci, Co) each
    if k * ci <= STACKED_TAPS_MAX_CHANNELS:
        planes = [jnp.concatenate(planes, axis=-1)]  # channel a * Ci + c is tap a, channel c
        kernels = [jnp.moveaxis(kernel, 0, 2).reshape(k, k, k * ci, -1)]
    out = None
    for plane, w in zip(planes, kernels, strict=True):
        plane = plane.reshape(b * nx, ny + 2 * p, nz + 2 * p, plane.shape[-1])
        y = jax.lax.conv_general_dilated(plane, w, (1, 1), "VALID", dimension_numbers=_NHWC)
        out = y if out is None else out + y
    return out.reshape(b, nx, ny, nz, kernel.shape[-1])


def space_to_depth(x: jax.Array) -> jax.Array:
    """(B, X, Y, Z, C) -> (B, X/2, Y/2, Z/2, 8C); each 2x2x2 cell gathered in (dx, dy, dz, c)."""
    b, nx, ny, nz, c = x.shape
    x = x.reshape(b, nx // 2, 2, ny // 2, 2, nz // 2, 2, c)
    return x.transpose(0, 1, 3, 5, 2, 4, 6, 7).reshape(b, nx // 2, ny // 2, nz // 2, 8 * c)


def depth_to_space(x: jax.Array) -> jax.Array:
    """Inverse of `space_to_depth`: (B, X, Y, Z, 8C) -> (B, 2X, 2Y, 2Z, C)."""
    b, nx, ny, nz, c8 = x.shape
    c = c8 // 8
    x = x.reshape(b, nx, ny, nz, 2, 2, 2, c).transpose(0, 1, 4, 2, 5, 3, 6, 7)
    return x.reshape(b, 2 * nx, 2 * ny, 2 * nz, c)


def lecun_normal(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """LeCun-normal (truncated at 2 std, fan-in over all but the last axis) weights, drawn with
    NumPy from a seed taken from `key`.

    Same distribution as `nnx.initializers.lecun_normal()`; jax.random would compile one sampler
    per distinct weight shape, which dominated model construction time on CPU.
    """
    seed = np.asarray(jax.random.key_data(key)).ravel().tolist()
    rng = np.random.default_rng(seed)
    w = rng.standard_normal(shape)
    bad = np.abs(w) > 2.0
    while bad.any():  # resample outside [-2, 2]: a truncated normal
        w[bad] = rng.standard_normal(int(bad.sum()))
        bad = np.abs(w) > 2.0
    fan_in = int(np.prod(shape[:-1]))
    std = np.sqrt(1.0 / fan_in) / 0.87962566103423978  # std of the unit normal truncated at 2
    return jnp.asarray(w * std, jnp.float32)


class Conv3D(nnx.Module):
    """3D convolution, channels-last, 'SAME' padding, kernel (k,k,k,in,out) and bias.

    kernel=k, stride=1: ordinary convolution (odd k). kernel=2, stride=2: strided convolution
    halving each axis ("pool"). transpose=True, kernel=2, stride=2: transposed convolution
    doubling each axis. Initialisation as `nnx.Conv` (LeCun normal, zero bias). The convolution
    runs in `compute_dtype` (static attribute, "float32" or "bfloat16"); the result is float32.
    """

    def __init__(
        self,
        in_ch: int,
        out_ch: int,
        kernel: int = 3,
        stride: int = 1,
        *,
        transpose: bool = False,
        rngs: nnx.Rngs,
    ):
        if stride not in (1, kernel) or (stride == kernel and kernel not in (1, 2)):
            raise ValueError(
                f"Conv3D supports stride 1, or kernel = stride = 2; got {kernel}, {stride}"
            )
        if transpose and (kernel, stride) != (2, 2):
            raise ValueError("Conv3D: transposed convolution only with kernel = stride = 2")
        self.kernel_size, self.stride, self.transpose = kernel, stride, transpose
        shape = (kernel, kernel, kernel, in_ch, out_ch)
        self.kernel = nnx.Param(lecun_normal(rngs.params(), shape))
        self.bias = nnx.Param(jnp.zeros((out_ch,), jnp.float32))
        self.compute_dtype = "float32"

    def __call__(self, x: jax.Array) -> jax.Array:
        x, w = in_compute_dtype(self.compute_dtype, x, self.kernel[...])
        k = self.kernel_size
        if k == 1:
            y = jnp.einsum("...i,io->...o", x, w[0, 0, 0])
        elif self.transpose:  # each input cell paints its own 2x2x2 block of the output
            y = depth_to_space(jnp.einsum("...i,abcio->...abco", x, w).reshape(*x.shape[:-1], -1))
        elif self.stride == 2:  # each output cell sees exactly one 2x2x2 block of the input
            y = space_to_depth(x) @ w.reshape(-1, w.shape[-1])
        else:
            y = conv3d_same(x, w)
        return y.astype(jnp.float32) + self.bias[...]


def set_compute_dtype(model: nnx.Module, name: str) -> None:
    """Sets `compute_dtype` of every `Conv3D` inside `model` ("float32" or "bfloat16")."""
    check_compute_dtype(name)
    for _, module in nnx.iter_modules(model):
        if isinstance(module, Conv3D):
            module.compute_dtype = name


class ConvNormAct(nnx.Module):
    """conv (kernel k, stride s, SAME padding) -> GroupNorm -> LeakyReLU."""

    def __init__(
        self, in_ch: int, out_ch: int, kernel: int = 3, stride: int = 1, *, rngs: nnx.Rngs
    ):
        self.conv = Conv3D(in_ch, out_ch, kernel, stride, rngs=rngs)
        self.norm = nnx.GroupNorm(out_ch, num_groups=num_groups(out_ch), rngs=rngs)

    def __call__(self, x: jax.Array) -> jax.Array:
        return nnx.leaky_relu(self.norm(self.conv(x)), LEAK)


class ResBlock(nnx.Module):
    """Residual block: two conv3 + GroupNorm, a 1x1x1 projection on the skip when widths differ."""

    def __init__(self, in_ch: int, out_ch: int, *, rngs: nnx.Rngs):
        self.conv1 = ConvNormAct(in_ch, out_ch, 3, rngs=rngs)
        self.conv2 = Conv3D(out_ch, out_ch, 3, rngs=rngs)
        self.norm2 = nnx.GroupNorm(out_ch, num_groups=num_groups(out_ch), rngs=rngs)
        self.skip = Conv3D(in_ch, out_ch, 1, rngs=rngs) if in_ch != out_ch else None

    def __call__(self, x: jax.Array) -> jax.Array:
        y = self.norm2(self.conv2(self.conv1(x)))
        skip = x if self.skip is None else self.skip(x)
        return nnx.leaky_relu(y + skip, LEAK)


class Pool(nnx.Module):
    """Strided 2x2x2 convolution halving each spatial axis, then GroupNorm + LeakyReLU."""

    def __init__(self, in_ch: int, out_ch: int, *, rngs: nnx.Rngs):
        self.block = ConvNormAct(in_ch, out_ch, kernel=2, stride=2, rngs=rngs)

    def __call__(self, x: jax.Array) -> jax.Array:
        return self.block(x)


class Upsample(nnx.Module):
    """Transposed 2x2x2 convolution doubling each spatial axis, then GroupNorm + LeakyReLU."""

    def __init__(self, in_ch: int, out_ch: int, *, rngs: nnx.Rngs):
        self.conv = Conv3D(in_ch, out_ch, 2, 2, transpose=True, rngs=rngs)
        self.norm = nnx.GroupNorm(out_ch, num_groups=num_groups(out_ch), rngs=rngs)

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
    """3D hourglass (Xu et al. 2019b style, paper Fig. 9): pool/residual levels down, transposed-
    conv upsampling back, a residual skip at every resolution added on the way up.

    With widths (32, 48, 72) and input width c: c@g -> 32@g/2 -> 48@g/4 -> 72@g/8 -> back to c@g.
    """

    def __init__(self, channels: int, widths: tuple[int, ...], size: int, *, rngs: nnx.Rngs):
        levels = hourglass_levels(size, len(widths))
        widths = (channels, *widths[:levels])
        self.down = nnx.List([_Down(widths[i], widths[i + 1], rngs=rngs) for i in range(levels)])
        self.skips = nnx.List([ResBlock(w, w, rngs=rngs) for w in widths[:levels]])
        self.bottom = ResBlock(widths[levels], widths[levels], rngs=rngs)
        self.up = nnx.List(
            [Upsample(widths[i + 1], widths[i], rngs=rngs) for i in reversed(range(levels))]
        )

    def __call__(self, x: jax.Array) -> jax.Array:
        skips = []
        for down, skip in zip(self.down, self.skips, strict=True):  # fixed depth, not data
            skips.append(skip(x))
            x = down(x)
        x = self.bottom(x)
        for up, skip in zip(self.up, reversed(skips), strict=True):
            x = up(x) + skip
        return x


class _Down(nnx.Module):
    """One hourglass level down: strided pool then a residual block changing the width."""

    def __init__(self, in_ch: int, out_ch: int, *, rngs: nnx.Rngs):
        self.pool = Pool(in_ch, in_ch, rngs=rngs)
        self.res = ResBlock(in_ch, out_ch, rngs=rngs)

    def __call__(self, x: jax.Array) -> jax.Array:
        return self.res(self.pool(x))


def upsample_trilinear(x: jax.Array) -> jax.Array:
    """(B, X, Y, Z, C) -> (B, 2X, 2Y, 2Z, C) by trilinear interpolation (half-pixel centres)."""
    b, nx, ny, nz, c = x.shape
    return jax.image.resize(x, (b, 2 * nx, 2 * ny, 2 * nz, c), method="linear")


class FeatureNet(nnx.Module):
    """f_feat of paper Fig. 9: (B, G, G, G) occupancy -> (B, g, g, g, C) features, g = G / stride.

    CoordConv conv5 on [occupancy, x, y, z] (-> C/4) + GN + LeakyReLU, pool, residual
    (C/4 -> C/2), pool (stride 4 only), hourglass at g, residual (C/2 -> C). The stem is linear
    in its input channels, so the three coordinate channels (identical for every sample) are
    convolved once and broadcast instead of being concatenated to every sample: the same
    function, 4x cheaper.
    """

    def __init__(
        self,
        channels: int,
        hourglass_channels: tuple[int, ...],
        grid: int,
        stride: int = 4,
        *,
        rngs: nnx.Rngs,
    ):
        check_heatmap_stride(stride)
        c4, c2 = max(1, channels // 4), max(1, channels // 2)
        self.stem = ConvNormAct(1 + 3, c4, kernel=5, rngs=rngs)
        self.pool1 = Pool(c4, c4, rngs=rngs)
        self.res1 = ResBlock(c4, c2, rngs=rngs)
        self.pool2 = Pool(c2, c2, rngs=rngs) if stride == 4 else None
        self.hourglass = Hourglass(c2, hourglass_channels, grid // stride, rngs=rngs)
        self.res2 = ResBlock(c2, channels, rngs=rngs)

    def __call__(self, voxels: jax.Array) -> jax.Array:
        dtype = self.stem.conv.compute_dtype
        w = self.stem.conv.kernel[...]  # (5, 5, 5, 1 + 3, C/4)
        coords = coord_grid(voxels.shape[1])[None]  # (1, G, G, G, 3)
        v, c, wv, wc = in_compute_dtype(
            dtype, voxels[..., None], coords, w[..., :1, :], w[..., 1:, :]
        )
        x = (conv3d_same(v, wv) + conv3d_same(c, wc)).astype(jnp.float32)
        x = nnx.leaky_relu(self.stem.norm(x + self.stem.conv.bias[...]), LEAK)
        x = self.res1(self.pool1(x))
        if self.pool2 is not None:
            x = self.pool2(x)
        return self.res2(self.hourglass(x))
