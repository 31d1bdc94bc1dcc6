"""3D convolution blocks of the keypoint detector (paper Fig. 9): channels-last (..., X, Y, Z, C).

Every block takes a batch (B, X, Y, Z, C); callers fold time into the batch axis.

`Conv3D` computes exactly the 3D convolution but, on CPU, not with XLA's 3D convolution, which is
3-10x slower there than its 2D convolution: a float32 3x3x3 kernel on a grid of side 8 or more is
evaluated by Winograd's F(4x4x4, 3x3x3) (`winograd_conv3d_valid`, 1/8 of the multiply-adds as
batched matmuls), any other stride-1 kernel as 2D convolutions over (y, z) with x folded into the
batch (`conv3d_same`); the strided
2x2x2 "pool" is a space-to-depth reshape and a matmul, the 2x2x2 transposed convolution a matmul
and a depth-to-space reshape. On GPU/TPU backends the native convolution is used. On CPU the
thin layers at the full grid (the stem, the convolutions after the decoder's upsamplings) run
on the half grid in 2x2x2 blocks (`blocked_kernel`, `upsample_conv3d_same`): the same function.

`Conv3D.compute_dtype` ("float32" or "bfloat16", set for a whole model by `set_compute_dtype`)
is the precision of the convolution itself: input and kernel are cast to it and the result cast
back to float32, so parameters, normalisation and everything downstream stay float32.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from nmjax.keypoints import axis_coords

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


def num_groups(channels: int) -> int:
    """GroupNorm groups: channels / 16 (DESIGN section 6), at least 1 and dividing `channels`."""
    return math.gcd(channels, max(1, channels // 16))


_NDHWC = ("NDHWC", "DHWIO", "NDHWC")
# On CPU, stride-1 convolutions run as 2D convolutions over (Y, Z) with X folded into the batch
# axis: with YNNPACK's convolutions switched off (nmjax/__init__.py), XLA's CPU 2D convolution
# beats its 3D convolution at every shape of the detector, forward + backward, by 2.5-15x (1 to
# 128 channels, 4^3 to 32^3 grids; docs/performance.md, "CPU convolutions"). The k taps along X
# are stacked on the channel axis: one 2D convolution with a k-times deeper kernel. Against one
# 2D convolution per tap it is as fast at the cpu preset's widths and makes the phase-1 step at
# the paper's channels 1.13x faster (docs/performance.md, "GroupNorm and stacked taps"); a k-times
# wider output (the taps' kernels side by side, the results shifted and summed) was faster for
# single convolutions of few output channels but slower in the step.
_NHWC = ("NHWC", "HWIO", "NHWC")
COMPUTE_DTYPES = ("float32", "bfloat16")
# G / g: f_feat pools twice (4) or once (2) before the hourglass; f_dec upsamples as often.
HEATMAP_STRIDES = (2, 4)


def cell_sums(x: jax.Array) -> jax.Array:
    """(N, S, C) -> (N, C): the sum over the S cells of each channel.

    XLA's CPU reduction over a middle axis keeps only the C minor values per row in flight;
    folding up to 64 consecutive cells into the minor axis first (one reduction over S / f rows
    of f C values, then one over f) is 1.3-1.6x faster forward + backward in GroupNorm, and its
    float32 sums are closer to float64 than a single long reduction.
    """
    n, s, c = x.shape
    fold = math.gcd(s, 64)
    return jnp.sum(x.reshape(n, s // fold, fold * c), axis=1).reshape(n, fold, c).sum(axis=1)


def _group_stats(flat: jax.Array, groups: int, eps: float) -> tuple[jax.Array, jax.Array]:
    """Mean and 1 / sqrt(var + eps), each (N, groups), of flat (N, S, C)."""
    n, _, c = flat.shape
    count = flat.shape[1] * (c // groups)
    mean = cell_sums(flat).reshape(n, groups, -1).sum(-1) / count
    mean_sq = cell_sums(flat * flat).reshape(n, groups, -1).sum(-1) / count
    return mean, jax.lax.rsqrt(jnp.maximum(mean_sq - mean * mean, 0.0) + eps)


@functools.partial(jax.custom_vjp, nondiff_argnums=(3, 4))
def group_norm(
    x: jax.Array, scale: jax.Array, bias: jax.Array, groups: int, eps: float = GN_EPS
) -> jax.Array:
    """GroupNorm (Wu & He 2018; the detector's norm, paper Fig. 9) of channels-last x.

    Args:
      x: (N, ..., C); statistics per sample over every cell (the middle axes) and the C / groups
        channels of each group.
      scale, bias: (C,) per-channel affine parameters.
      groups: number of groups, dividing C.
      eps: added to the variance.

    Returns:
      (N, ..., C) (x - mean) / sqrt(var + eps) * scale + bias, var = E[x^2] - E[x]^2 (floored
      at 0), as `flax.nnx.GroupNorm` computes it.

    Every reduction is a per-channel sum (`cell_sums`) and the rest is one multiply-add per
    element with per-(sample, channel) coefficients, forward and backward (a hand-written VJP:
    XLA fuses the autodiff form's five reductions each with a recomputation of the forward and
    of the incoming gradient, re-reading the inputs in every one of them).
    """
    return _group_norm_fwd(x, scale, bias, groups, eps)[0]


def _group_norm_fwd(x, scale, bias, groups, eps):
    n, c = x.shape[0], x.shape[-1]
    if c % groups:
        raise ValueError(f"group_norm: {groups} groups do not divide {c} channels")
    flat = x.reshape(n, -1, c)
    mean, inv = _group_stats(flat, groups, eps)
    a = jnp.repeat(inv, c // groups, axis=1) * scale  # (N, C)
    b = bias - jnp.repeat(mean, c // groups, axis=1) * a
    return (flat * a[:, None] + b[:, None]).reshape(x.shape), (x, scale, mean, inv)


def _group_norm_bwd(groups, eps, residuals, g):
    del eps
    x, scale, mean, inv = residuals
    n, c = x.shape[0], x.shape[-1]
    per = c // groups
    flat, g = x.reshape(n, -1, c), g.reshape(n, -1, c)
    count = flat.shape[1] * per
    sum_g = cell_sums(g)  # (N, C)
    mean_c, inv_c = jnp.repeat(mean, per, axis=1), jnp.repeat(inv, per, axis=1)
    sum_g_xhat = inv_c * (cell_sums(g * flat) - mean_c * sum_g)  # sum of g * normalised x
    # d/dx of the normalisation: inv (g scale - mean over the group of g scale - xhat * mean
    # over the group of g scale xhat), written as g a + x b + d with (N, C) coefficients.
    p = (scale * sum_g).reshape(n, groups, per).sum(-1) / count  # (N, groups)
    q = (scale * sum_g_xhat).reshape(n, groups, per).sum(-1) / count
    a = inv_c * scale
    b = jnp.repeat(-inv * inv * q, per, axis=1)
    d = jnp.repeat(inv * (inv * q * mean - p), per, axis=1)
    dx = g * a[:, None] + flat * b[:, None] + d[:, None]
    return dx.reshape(x.shape), sum_g_xhat.sum(0), sum_g.sum(0)


group_norm.defvjp(_group_norm_fwd, _group_norm_bwd)


class GroupNorm(nnx.GroupNorm):
    """`flax.nnx.GroupNorm` (same parameters, same function: statistics over every axis but the
    first and the last) evaluated by `group_norm`. On CPU its forward + backward (with the
    LeakyReLU after it) is 1.3x faster than flax's at the cpu preset's shapes and 2.7-4x at the
    paper's channels, where flax's reductions took a tenth of the phase-1 step."""

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


# The forms that run on the CPU layouts (the full-grid rewrites below apply to all of them).
CPU_FORMS = ("per_tap", "stacked", "winograd")
CONV_FORMS = ("auto", "native", *CPU_FORMS)
CPU_CONV_FORM = "winograd"  # what "auto" takes on CPU for a float32 3x3x3 kernel
CPU_FALLBACK_FORM = "stacked"  # for other kernels and dtypes, and small grids


def conv_form() -> str:
    """The form `conv3d_same(form="auto")` takes on this backend: "native" on GPU/TPU,
    `CPU_CONV_FORM` on CPU (which falls back to `CPU_FALLBACK_FORM` where it does not apply)."""
    return "native" if jax.default_backend() != "cpu" else CPU_CONV_FORM


WINOGRAD_MIN_SIDE = 8  # "auto": below it, whole tiles of 4^3 outputs waste most of their work


def winograd_applies(kernel: jax.Array) -> bool:
    """Whether the Winograd form evaluates `kernel`: 3x3x3 and float32 (in bfloat16 the input
    transform, with coefficients up to 5, would lose the few digits bfloat16 has)."""
    return kernel.shape[:3] == (3, 3, 3) and kernel.dtype == jnp.float32


def _check_conv_args(name: str, k: int, form: str) -> None:
    """Raises ValueError unless the kernel size `k` is odd and `form` is one of CONV_FORMS."""
    if k % 2 == 0:
        raise ValueError(f"{name} needs an odd kernel size, got {k}")
    if form not in CONV_FORMS:
        raise ValueError(f"{name}: form must be one of {CONV_FORMS}, got {form!r}")


def conv3d_same(x: jax.Array, kernel: jax.Array, form: str = "auto") -> jax.Array:
    """Stride-1 'SAME' 3D convolution (cross-correlation) of x (B,X,Y,Z,Ci) with (k,k,k,Ci,Co).

    Odd k only. Every form computes the same function:
      "native": XLA's 3D convolution.
      "per_tap": 2D convolutions over (Y, Z) with X folded into the batch axis, one per offset a
        along X of the shifted planes x[:, a : a + X] (a fixed loop over kernel taps, not over
        data), summed.
      "stacked": the k shifted planes concatenated on the channel axis into a single 2D
        convolution with a k-times deeper kernel.
      "winograd": Winograd's minimal filtering F(4x4x4, 3x3x3) (`winograd_conv3d_valid`), for
        a float32 3x3x3 kernel; other kernels take `CPU_FALLBACK_FORM`.
      "auto": the fastest of these on this backend (`conv_form`).
    """
    k = kernel.shape[0]
    _check_conv_args("conv3d_same", k, form)
    if form == "native" or (form == "auto" and conv_form() == "native"):
        return jax.lax.conv_general_dilated(x, kernel, (1, 1, 1), "SAME", dimension_numbers=_NDHWC)
    p = k // 2
    return conv3d_valid(jnp.pad(x, ((0, 0), (p, p), (p, p), (p, p), (0, 0))), kernel, form)


def conv3d_valid(padded: jax.Array, kernel: jax.Array, form: str = "auto") -> jax.Array:
    """'VALID' 3D convolution (cross-correlation) of an already padded input.

    padded (B, X + k - 1, Y + k - 1, Z + k - 1, Ci) with kernel (k, k, k, Ci, Co), odd k, ->
    (B, X, Y, Z, Co); `form` as in `conv3d_same`.
    """
    k = kernel.shape[0]
    _check_conv_args("conv3d_valid", k, form)
    p = k // 2
    b, nx, ny, nz, ci = padded.shape
    nx, ny, nz = nx - 2 * p, ny - 2 * p, nz - 2 * p
    if form == "auto":
        form = conv_form()
        if form == "winograd" and min(nx, ny, nz) < WINOGRAD_MIN_SIDE:
            form = CPU_FALLBACK_FORM
    if form == "winograd":
        if winograd_applies(kernel):
            return winograd_conv3d_valid(padded, kernel)
        form = CPU_FALLBACK_FORM
    if form == "native":
        return jax.lax.conv_general_dilated(
            padded, kernel, (1, 1, 1), "VALID", dimension_numbers=_NDHWC
        )
    if form == "stacked":
        planes = [stacked_planes(padded, k)]
        kernels = [jnp.moveaxis(kernel, 0, 2).reshape(k, k, k * ci, -1)]
    else:
        planes = [padded[:, a : a + nx] for a in range(k)]  # (B, X, Y + 2p, Z + 2p, Ci) each
        kernels = list(kernel)  # (k, k, Ci, Co) each
    out = None
    for plane, w in zip(planes, kernels, strict=True):
        plane = plane.reshape(b * nx, ny + 2 * p, nz + 2 * p, plane.shape[-1])
        y = jax.lax.conv_general_dilated(plane, w, (1, 1), "VALID", dimension_numbers=_NHWC)
        out = y if out is None else out + y
    return out.reshape(b, nx, ny, nz, kernel.shape[-1])


@functools.partial(jax.custom_vjp, nondiff_argnums=(1,))
def stacked_planes(padded: jax.Array, k: int) -> jax.Array:
    """The k planes padded[:, a : a + X] (X = padded's first side - k + 1) concatenated on the
    channel axis: (B, X + k - 1, Y, Z, C) -> (B, X, Y, Z, k C), channel a * C + c.

    Differentiated by adding the k channel slices of the cotangent into one zero tensor in
    place: the transpose of k slices is k full-size padded tensors, which XLA sums inside every
    consumer of the input gradient, re-reading all k in each of them (the bias and norm gradient
    reductions before it).
    """
    nx = padded.shape[1] - k + 1
    return jnp.concatenate([padded[:, a : a + nx] for a in range(k)], axis=-1)


def _stacked_planes_fwd(padded: jax.Array, k: int) -> tuple[jax.Array, tuple[int, ...]]:
    return stacked_planes(padded, k), padded.shape


def _stacked_planes_bwd(k: int, shape: tuple[int, ...], g: jax.Array) -> tuple[jax.Array]:
    nx, c = shape[1] - k + 1, shape[-1]
    out = jnp.zeros(shape, g.dtype)
    for a in range(k):
        out = out.at[:, a : a + nx].add(g[..., a * c : (a + 1) * c])
    return (out,)


stacked_planes.defvjp(_stacked_planes_fwd, _stacked_planes_bwd)


# Winograd's minimal filtering F(4, 3) (Lavin & Gray 2016, "Fast algorithms for convolutional
# neural networks"), nested over the three axes: a 6-cell input tile d gives 4 outputs of a
# 3-tap correlation g as A^T [(G g) * (B^T d)], 6 multiplications instead of 12 per axis, so a
# 3x3x3 convolution costs 216 / 64 = 3.4 multiply-adds per output and input channel pair
# instead of 27. The channel mixing becomes 216 independent matmuls, one per tile position.
# Interpolation points 0, +-1, +-2 (the last row and column of B^T stand for infinity).
_WINOGRAD_BT = np.array(
    [
        [4, 0, -5, 0, 1, 0],
        [0, -4, -4, 1, 1, 0],
        [0, 4, -4, -1, 1, 0],
        [0, -2, -1, 2, 1, 0],
        [0, 2, -1, -2, 1, 0],
        [0, 4, 0, -5, 0, 1],
    ],
    np.float32,
)
_WINOGRAD_G = np.array(
    [
        [1 / 4, 0, 0],
        [-1 / 6, -1 / 6, -1 / 6],
        [-1 / 6, 1 / 6, -1 / 6],
        [1 / 24, 1 / 12, 1 / 6],
        [1 / 24, -1 / 12, 1 / 6],
        [0, 0, 1],
    ],
    np.float32,
)
_WINOGRAD_AT = np.array(
    [[1, 1, 1, 1, 1, 0], [0, 1, -1, 2, -2, 0], [0, 1, 1, 4, 4, 0], [0, 1, -1, 8, -8, 1]],
    np.float32,
)
WINOGRAD_TILE = 4  # outputs per tile along each axis


def _constant_combinations(matrix: np.ndarray, parts: list[jax.Array]) -> jax.Array:
    """jnp.stack([sum_j matrix[i, j] * parts[j] for each row i]): written term by term without
    the zero coefficients, so that XLA fuses the whole transform into one elementwise pass."""
    rows = []
    for row in matrix:
        acc = None
        for c, part in zip(row.tolist(), parts, strict=True):
            if c == 0:
                continue
            term = part if c == 1 else -part if c == -1 else part * c
            acc = term if acc is None else acc + term
        rows.append(acc)
    return jnp.stack(rows)


@functools.partial(jax.custom_vjp, nondiff_argnums=(1,))
def _winograd_input_transform(padded: jax.Array, axis: int) -> jax.Array:
    """B^T applied to every input tile along `axis`: (..., 4T + 2, ...) -> (6, ..., T, ...), the
    tile position first. Tile t reads cells 4t .. 4t + 5 (tiles overlap by two cells).

    Differentiated by hand: autodiff's transpose of the six strided slices is six padded
    full-size tensors summed; the VJP instead forms the six combinations B g and overlap-adds
    them into one interleaved tensor.
    """
    m = WINOGRAD_TILE
    t = (padded.shape[axis] - 2) // m
    parts = [jax.lax.slice_in_dim(padded, j, j + m * (t - 1) + 1, m, axis) for j in range(m + 2)]
    return _constant_combinations(_WINOGRAD_BT, parts)


def _winograd_input_transform_fwd(padded: jax.Array, axis: int) -> tuple[jax.Array, int]:
    return _winograd_input_transform(padded, axis), padded.shape[axis]


def _winograd_input_transform_bwd(axis: int, side: int, g: jax.Array) -> tuple[jax.Array]:
    m = WINOGRAD_TILE
    parts = _constant_combinations(_WINOGRAD_BT.T, list(g))  # (6, ..., T, ...): cell 4t + j

    def shifted(part: jax.Array, low: int) -> jax.Array:  # T -> T + 1 cells along `axis`
        widths = [(0, 0)] * part.ndim
        widths[axis] = (low, 1 - low)
        return jnp.pad(part, widths)

    # Cell 4s + j receives part j of tile s and, for j < 2, part j + 4 of tile s - 1.
    phases = [shifted(parts[j], 0) + (shifted(parts[j + m], 1) if j < 2 else 0) for j in range(m)]
    out = jnp.stack(phases, axis=axis + 1)  # (..., T + 1, 4, ...)
    shape = out.shape
    out = out.reshape(*shape[:axis], shape[axis] * m, *shape[axis + 2 :])
    return (jax.lax.slice_in_dim(out, 0, side, axis=axis),)


_winograd_input_transform.defvjp(_winograd_input_transform_fwd, _winograd_input_transform_bwd)


def _winograd_output_transform(y: jax.Array, axis: int) -> jax.Array:
    """A^T over the leading tile-position axis of y (6, ..., T, ...) (tiles on `axis` of y),
    the 4 outputs of each tile interleaved in order: -> (..., 4T, ...)."""
    out = _constant_combinations(_WINOGRAD_AT, list(y))  # (4, ..., T, ...), tiles on axis - 1
    out = jnp.moveaxis(out, 0, axis)  # right after the tile axis
    shape = out.shape
    return out.reshape(*shape[: axis - 1], shape[axis - 1] * WINOGRAD_TILE, *shape[axis + 1 :])


def winograd_kernel(kernel: jax.Array) -> jax.Array:
    """(3, 3, 3, Ci, Co) -> (216, Ci, Co): G g G^T along each axis, tile position (z, y, x)
    flattened in the order `winograd_conv3d_valid` stacks its input tiles."""
    g = jnp.asarray(_WINOGRAD_G, kernel.dtype)
    w = jnp.einsum("ai,bj,ck,ijkxo->cbaxo", g, g, g, kernel)
    return w.reshape(-1, *kernel.shape[3:])


def winograd_conv3d_valid(padded: jax.Array, kernel: jax.Array) -> jax.Array:
    """'VALID' 3x3x3 convolution by Winograd's F(4x4x4, 3x3x3): `conv3d_valid`'s function.

    Args:
      padded: (B, X + 2, Y + 2, Z + 2, Ci), any sides (zero-extended to whole tiles of 4
        outputs, and the extra outputs cropped).
      kernel: (3, 3, 3, Ci, Co).

    Returns:
      (B, X, Y, Z, Co).

    Input tiles of 6^3 cells (stride 4) are transformed by B^T along each axis, multiplied
    with the transformed kernel (216 matmuls of (B * tiles, Ci) by (Ci, Co), one batched
    `einsum`), and transformed back by A^T. It does 1/8 of the direct form's multiply-adds in
    the matmuls, at the price of transformed tiles 3.4x the input's size. The interpolation
    points +-2 make it less exact than the direct sum: float32 results are about 1e-5 off
    relative to the largest output, against 1e-7 for the direct forms. Every step is linear,
    so the gradients are the transposed transforms and matmuls: autodiff's, except for the
    input transform's hand-written VJP (`_winograd_input_transform`).
    """
    m = WINOGRAD_TILE
    b, *sides, ci = padded.shape
    outs = [s - 2 for s in sides]
    tiles = [-(-o // m) for o in outs]
    extra = [(0, 0)] + [(0, m * t - o) for t, o in zip(tiles, outs, strict=True)] + [(0, 0)]
    u = jnp.pad(padded, extra)
    for axis in (1, 3, 5):  # x, y, z; each transform puts its tile position first
        u = _winograd_input_transform(u, axis)
    u = u.reshape(6**3, -1, ci)  # (z, y, x positions, B * tiles, Ci)
    y = jnp.einsum("pmi,pio->pmo", u, winograd_kernel(kernel))
    y = y.reshape(6, 6, 6, b, *tiles, kernel.shape[-1])
    for axis in (6, 4, 2):  # z, y, x
        y = _winograd_output_transform(y, axis)
    return y[:, : outs[0], : outs[1], : outs[2]]


def coord_conv3d_same(kernel: jax.Array, n: int) -> jax.Array:
    """`conv3d_same(coord_grid(n)[None], kernel)[0]`, (k,k,k,3,Co) -> (n,n,n,Co), in closed form.

    Coordinate channel d is the ramp linspace(-1, 1, n) along axis d and constant along the two
    others, so with zero padding its convolution is a sum of separable terms:
    out[x, y, z] = sum_abc w[a, b, c] R_a(x) M_b(y) M_c(z) for d = 0 (and likewise for d = 1, 2),
    where R_a(x) is the ramp at x + a - k//2 (0 outside the grid) and M_a the same for a constant 1.
    Three small contractions per channel instead of a 3D convolution over the grid: exact, and
    in the step's forward and kernel gradient it replaced two convolutions that cost 15% of the
    cpu preset's phase-1 step.
    """
    k = kernel.shape[0]
    p = k // 2
    shift = jnp.arange(k)[:, None] + jnp.arange(n)[None, :] - p  # (k, n): cell seen by tap a at x
    inside = (shift >= 0) & (shift < n)
    ramp = jnp.where(inside, axis_coords(n)[jnp.clip(shift, 0, n - 1)], 0.0)
    ones = inside.astype(kernel.dtype)
    ramp = ramp.astype(kernel.dtype)
    out = 0.0
    for d in range(3):  # the three coordinate channels: a fixed loop, not over data
        fx, fy, fz = (ramp if d == axis else ones for axis in range(3))
        out = out + jnp.einsum("ax,by,cz,abco->xyzo", fx, fy, fz, kernel[:, :, :, d, :])
    return out


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


# Full-grid layers on CPU. The detector's layers at the full grid G^3 have 1-8 channels, where
# every form of XLA's CPU convolution spends its time in copies and transposes rather than in
# arithmetic. Two exact rewrites move them to the G/2 grid with 8x the channels, in 2x2x2 blocks
# (the `space_to_depth` layout), which XLA's 2D convolutions handle well:
# - a stride-1 convolution of a thin input equals a k=3 convolution of its blocks with a
#   block-structured kernel (`blocked_kernel`); the FeatureNet stem (1 -> C/4 channels, k=5)
#   costs 1.7x the arithmetic that way and runs 2.8x faster, and its output feeds the first
#   strided pool, which reads blocks anyway;
# - a k=3 convolution after a 2x trilinear upsampling equals one k=3 convolution of the coarse
#   input that writes the 8 output phases of each block (`upsample_conv3d_same`), with the same
#   arithmetic as the fine convolution and no fine input at all (the decoder's two upsampling
#   stages).


def uses_cpu_rewrites(form: str) -> bool:
    """Whether a `Conv3D` with `conv_form` = `form` runs in one of the CPU forms on this backend,
    and so takes the full-grid rewrites above ("native" and non-CPU backends keep the plain
    layers)."""
    return (conv_form() if form == "auto" else form) in CPU_FORMS


def _block_taps(k: int) -> np.ndarray:
    """(3, 2, 2, k) 0/1 array along one axis: S[a, p, q, f] = 1 when kernel tap f carries input
    phase p of coarse cell i + a - 1 to output phase q of coarse cell i, i.e. when the fine
    offset f - k//2 equals 2 (a - 1) + p - q. Covers every tap for odd k <= 5."""
    s = np.zeros((3, 2, 2, k), np.float32)
    for a, p, q in np.ndindex(3, 2, 2):
        f = 2 * (a - 1) + p - q + k // 2
        if 0 <= f < k:
            s[a, p, q, f] = 1.0
    return s


def blocked_kernel(kernel: jax.Array) -> jax.Array:
    """The kernel of the same convolution acting on 2x2x2 blocks.

    (k, k, k, Ci, Co), odd k <= 5 -> (3, 3, 3, 8 Ci, 8 Co) such that, for x with even sides,
    conv3d_same(space_to_depth(x), blocked_kernel(w)) == space_to_depth(conv3d_same(x, w)).
    The block kernel is zero where a tap does not link two phases: (6/k)^3 times the arithmetic.
    """
    k, ci, co = kernel.shape[0], kernel.shape[3], kernel.shape[4]
    if k % 2 == 0 or k > 5:
        raise ValueError(f"blocked_kernel needs an odd kernel size <= 5, got {k}")
    s = jnp.asarray(_block_taps(k), kernel.dtype)
    w = jnp.einsum("apqf,bsrg,cuvh,fghio->abcpsuiqrvo", s, s, s, kernel)
    return w.reshape(3, 3, 3, 8 * ci, 8 * co)


def _upsample_taps() -> np.ndarray:
    """(3, 2, 3) along one axis: U[d, q, e] is the weight of coarse cell i + e - 1 in the value
    that tap d of a k=3 convolution reads for output phase q of coarse cell i, when the
    convolution follows `upsample_trilinear`. Tap d reads fine cell f = 2i + q + d - 1, which
    half-pixel linear upsampling fills with 0.25 x[m-1] + 0.75 x[m] (f = 2m) or
    0.75 x[m] + 0.25 x[m+1] (f = 2m + 1)."""
    u = np.zeros((3, 2, 3), np.float32)
    for d, q in np.ndindex(3, 2):
        f = q + d - 1  # fine offset from 2i: -1..2
        m = f // 2
        near, far = (m, m - 1) if f % 2 == 0 else (m, m + 1)
        u[d, q, near + 1] += 0.75
        u[d, q, far + 1] += 0.25
    return u


def upsample_conv_kernel(kernel: jax.Array) -> jax.Array:
    """(3, 3, 3, Ci, Co) -> (3, 3, 3, Ci, 8 Co): the k=3 kernel on the coarse grid whose output
    channel (qx, qy, qz, o) is output phase (qx, qy, qz) of `kernel` applied after a 2x trilinear
    upsampling (away from the grid's faces; `upsample_conv3d_same` corrects those)."""
    if kernel.shape[:3] != (3, 3, 3):
        raise ValueError(f"upsample_conv_kernel needs a 3x3x3 kernel, got {kernel.shape}")
    u = jnp.asarray(_upsample_taps(), kernel.dtype)
    w = jnp.einsum("dqe,frg,hsj,dfhio->egjiqrso", u, u, u, kernel)
    return w.reshape(3, 3, 3, kernel.shape[3], 8 * kernel.shape[4])


def upsample_conv3d_same(x: jax.Array, kernel: jax.Array, form: str = "auto") -> jax.Array:
    """space_to_depth(conv3d_same(upsample_trilinear(x), kernel)) without the upsampled grid.

    Args:
      x: (B, X, Y, Z, Ci) coarse input.
      kernel: (3, 3, 3, Ci, Co).
      form: the 2D-convolution form of the coarse convolution (`conv3d_valid`).

    Returns:
      (B, X, Y, Z, 8 Co): the fine result in 2x2x2 blocks, channel (qx, qy, qz, o).

    The upsampling is linear, so the two compose into one k=3 convolution on the coarse grid
    (`upsample_conv_kernel`). Padding x by edge replication makes that convolution see the
    upsampled grid padded by edge replication too (linear upsampling clamps at the faces), where
    the fine convolution sees zeros; the difference reaches only the outermost fine planes and is
    subtracted face by face, each a 2D convolution of the replicated face plane with the kernel's
    outer slice. Exact up to float rounding.
    """
    b, nx, ny, nz, _ = x.shape
    co = kernel.shape[-1]
    padded = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (1, 1), (0, 0)), mode="edge")
    y = conv3d_valid(padded, upsample_conv_kernel(kernel), form).reshape(b, nx, ny, nz, 2, 2, 2, co)

    def face(plane: jax.Array, w: jax.Array, replicated: int) -> jax.Array:
        """One face's share: the coarse face plane (B, m1, m2, Ci) upsampled, padded by one fine
        cell (replicated along the last `replicated` in-plane axes; zero along the others, whose
        shell cells belong to another face) and convolved -> (B, m1, m2, 2, 2, Co) in blocks."""
        m1, m2 = plane.shape[1:3]
        fine = jax.image.resize(plane, (b, 2 * m1, 2 * m2, plane.shape[-1]), "linear")
        for axis in (1, 2):
            widths = [(0, 0)] * 4
            widths[axis] = (1, 1)
            fine = jnp.pad(fine, widths, mode="edge" if axis > 2 - replicated else "constant")
        out = jax.lax.conv_general_dilated(fine, w, (1, 1), "VALID", dimension_numbers=_NHWC)
        return out.reshape(b, m1, 2, m2, 2, co).transpose(0, 1, 3, 2, 4, 5)

    planes = face_planes(x)  # (low, high) of x, then of y, then of z
    for axis in range(3):
        for q in (0, 1):  # the low and the high face
            i = 0 if q == 0 else -1
            w = jax.lax.index_in_dim(kernel, 2 * q, axis, keepdims=False)
            correction = face(planes[2 * axis + q], w, 2 - axis)
            index = (slice(None),) * (1 + axis) + (i,) + (slice(None),) * 2 + (q,)
            y = y.at[index].add(-correction)
    return y.reshape(b, nx, ny, nz, 8 * co)


@jax.custom_vjp
def face_planes(x: jax.Array) -> tuple[jax.Array, ...]:
    """The six boundary planes of x (B, X, Y, Z, C): x[:, 0], x[:, -1], x[:, :, 0], ... .

    Differentiated by writing the six plane gradients into one zero tensor: the transpose of
    six separate slices is six full-size padded tensors, which on CPU cost more than the
    convolutions of the planes themselves.
    """
    return tuple(jax.lax.index_in_dim(x, i, axis, False) for axis in (1, 2, 3) for i in (0, -1))


def _face_planes_fwd(x: jax.Array) -> tuple[tuple[jax.Array, ...], tuple[int, ...]]:
    return face_planes(x), x.shape


def _face_planes_bwd(shape: tuple[int, ...], grads: tuple[jax.Array, ...]) -> tuple[jax.Array]:
    out = jnp.zeros(shape, grads[0].dtype)
    for n, g in enumerate(grads):
        axis, i = 1 + n // 2, (0, -1)[n % 2]
        out = out.at[(slice(None),) * axis + (i,)].add(g)
    return (out,)


face_planes.defvjp(_face_planes_fwd, _face_planes_bwd)


def normal_init(key: jax.Array, shape: tuple[int, ...], std: float) -> jax.Array:
    """N(0, std^2) weights of `shape`, drawn with NumPy from a seed taken from `key`.

    jax.random would compile one sampler per distinct weight shape, which dominated model
    construction time on CPU.
    """
    seed = np.asarray(jax.random.key_data(key)).ravel().tolist()
    return jnp.asarray(np.random.default_rng(seed).normal(0.0, std, shape), jnp.float32)


class Conv3D(nnx.Module):
    """3D convolution, channels-last, 'SAME' padding, kernel (k,k,k,in,out) and bias.

    kernel=k, stride=1: ordinary convolution (odd k). kernel=2, stride=2: strided convolution
    halving each axis ("pool"). transpose=True, kernel=2, stride=2: transposed convolution
    doubling each axis. Kernel initialised N(0, init_std^2) (`INIT_STD`, the released
    network's), bias 0. The convolution
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
        init_std: float = INIT_STD,
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
        self.kernel = nnx.Param(normal_init(rngs.params(), shape, init_std))
        self.bias = nnx.Param(jnp.zeros((out_ch,), jnp.float32))
        self.compute_dtype = "float32"
        self.conv_form = "auto"  # how a stride-1 kernel is evaluated: `conv3d_same`'s `form`

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
            y = conv3d_same(x, w, self.conv_form)
        return y.astype(jnp.float32) + self.bias[...]

    def on_blocks(self, blocks: jax.Array) -> jax.Array:
        """The strided 2x2x2 convolution of an input given in 2x2x2 blocks (`space_to_depth`
        layout, (B, X/2, Y/2, Z/2, 8 Ci)): `self(depth_to_space(blocks))` without the fine grid."""
        if (self.kernel_size, self.stride, self.transpose) != (2, 2, False):
            raise ValueError("Conv3D.on_blocks: only the strided 2x2x2 convolution reads blocks")
        x, w = in_compute_dtype(self.compute_dtype, blocks, self.kernel[...])
        return (x @ w.reshape(-1, w.shape[-1])).astype(jnp.float32) + self.bias[...]


def norm_act_on_blocks(norm: GroupNorm, blocks: jax.Array) -> jax.Array:
    """GroupNorm + LeakyReLU of a tensor in 2x2x2 blocks (B, X, Y, Z, 8 C): the same statistics
    as on the fine grid, since a group's cells are the same cells in either layout."""
    shape = blocks.shape
    x = norm(blocks.reshape(*shape[:-1], 8, shape[-1] // 8))
    return nnx.leaky_relu(x, LEAK).reshape(shape)


def set_compute_dtype(model: nnx.Module, name: str) -> None:
    """Sets `compute_dtype` of every `Conv3D` inside `model` ("float32" or "bfloat16")."""
    check_compute_dtype(name)
    for _, module in nnx.iter_modules(model):
        if isinstance(module, Conv3D):
            module.compute_dtype = name


def set_conv_form(model: nnx.Module, form: str) -> None:
    """Sets how every stride-1 `Conv3D` inside `model` evaluates its kernel (`conv3d_same`'s
    `form`: "auto", the default, or "native", "per_tap", "stacked" to compare the forms)."""
    if form not in CONV_FORMS:
        raise ValueError(f"conv form must be one of {CONV_FORMS}, got {form!r}")
    for _, module in nnx.iter_modules(model):
        if isinstance(module, Conv3D):
            module.conv_form = form


class ConvNormAct(nnx.Module):
    """conv (kernel k, stride s, SAME padding) -> GroupNorm -> LeakyReLU."""

    def __init__(
        self,
        in_ch: int,
        out_ch: int,
        kernel: int = 3,
        stride: int = 1,
        *,
        init_std: float = INIT_STD,
        rngs: nnx.Rngs,
    ):
        self.conv = Conv3D(in_ch, out_ch, kernel, stride, init_std=init_std, rngs=rngs)
        self.norm = group_norm_layer(out_ch, rngs)

    def __call__(self, x: jax.Array) -> jax.Array:
        return nnx.leaky_relu(self.norm(self.conv(x)), LEAK)

    def after_upsampling(self, x: jax.Array) -> jax.Array:
        """`self(upsample_trilinear(x))` for a stride-1 k=3 block; where convolutions run in 2D,
        convolved on the coarse grid (`upsample_conv3d_same`) without forming the upsampled one.
        The norm follows on the fine layout: its backward then reads the incoming gradient in
        order (on the blocks, each of its reductions read it transposed; 1.2x slower at the
        paper's channels).

        x (B, X, Y, Z, Ci) -> (B, 2X, 2Y, 2Z, Co).
        """
        conv = self.conv
        if not uses_cpu_rewrites(conv.conv_form) or conv.kernel_size != 3 or conv.stride != 1:
            return self(upsample_trilinear(x))
        x, w = in_compute_dtype(conv.compute_dtype, x, conv.kernel[...])
        y = depth_to_space(upsample_conv3d_same(x, w, conv.conv_form).astype(jnp.float32))
        return nnx.leaky_relu(self.norm(y + conv.bias[...]), LEAK)


class ResBlock(nnx.Module):
    """Residual block as released: conv3-GN-LeakyReLU-conv3-GN on one branch, the identity or a
    1x1x1 projection + GroupNorm (when widths differ) on the skip, and branch + skip returned
    with no activation after the sum (the release's `leaky_relu(res + skip, True)` passes True as
    the negative slope: the identity). The output can be negative."""

    def __init__(
        self, in_ch: int, out_ch: int, *, init_std: float = FEATURE_INIT_STD, rngs: nnx.Rngs
    ):
        self.conv1 = ConvNormAct(in_ch, out_ch, 3, init_std=init_std, rngs=rngs)
        self.conv2 = Conv3D(out_ch, out_ch, 3, init_std=init_std, rngs=rngs)
        self.norm2 = group_norm_layer(out_ch, rngs)
        self.skip = (
            SkipProjection(in_ch, out_ch, init_std=init_std, rngs=rngs) if in_ch != out_ch else None
        )

    def __call__(self, x: jax.Array) -> jax.Array:
        y = self.norm2(self.conv2(self.conv1(x)))
        return y + (x if self.skip is None else self.skip(x))


class SkipProjection(nnx.Module):
    """The skip of a residual block that changes width: 1x1x1 conv, then GroupNorm."""

    def __init__(self, in_ch: int, out_ch: int, *, init_std: float, rngs: nnx.Rngs):
        self.conv = Conv3D(in_ch, out_ch, 1, init_std=init_std, rngs=rngs)
        self.norm = group_norm_layer(out_ch, rngs)

    def __call__(self, x: jax.Array) -> jax.Array:
        return self.norm(self.conv(x))


class Pool(nnx.Module):
    """Strided 2x2x2 convolution halving each spatial axis, then GroupNorm + LeakyReLU."""

    def __init__(
        self, in_ch: int, out_ch: int, *, init_std: float = FEATURE_INIT_STD, rngs: nnx.Rngs
    ):
        self.block = ConvNormAct(in_ch, out_ch, kernel=2, stride=2, init_std=init_std, rngs=rngs)

    def __call__(self, x: jax.Array) -> jax.Array:
        return self.block(x)

    def on_blocks(self, blocks: jax.Array) -> jax.Array:
        """`self(depth_to_space(blocks))` for an input already in 2x2x2 blocks."""
        return nnx.leaky_relu(self.block.norm(self.block.conv.on_blocks(blocks)), LEAK)


class Upsample(nnx.Module):
    """Transposed 2x2x2 convolution doubling each spatial axis, then GroupNorm + LeakyReLU."""

    def __init__(
        self, in_ch: int, out_ch: int, *, init_std: float = FEATURE_INIT_STD, rngs: nnx.Rngs
    ):
        self.conv = Conv3D(in_ch, out_ch, 2, 2, transpose=True, init_std=init_std, rngs=rngs)
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

    def __init__(self, channels: int, widths: tuple[int, ...], size: int, *, rngs: nnx.Rngs):
        levels = hourglass_levels(size, len(widths))
        widths = (channels, *widths[:levels])
        self.down = nnx.List([_Down(widths[i], widths[i + 1], rngs=rngs) for i in range(levels)])
        self.skips = nnx.List([ResBlock(w, w, rngs=rngs) for w in widths[:levels]])
        # up_res[j] runs before up[j]: widths 72, 48, 32 for the paper's hourglass.
        self.up_res = nnx.List(
            [ResBlock(widths[i + 1], widths[i + 1], rngs=rngs) for i in reversed(range(levels))]
        )
        self.up = nnx.List(
            [Upsample(widths[i + 1], widths[i], rngs=rngs) for i in reversed(range(levels))]
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
    convolved once, in closed form (`coord_conv3d_same`), and broadcast instead of being
    concatenated to every sample: the same function, 4x cheaper.
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
        self.stem = ConvNormAct(1 + 3, c4, kernel=5, init_std=FEATURE_INIT_STD, rngs=rngs)
        self.pool1 = Pool(c4, c4, rngs=rngs)
        self.res1 = ResBlock(c4, c2, rngs=rngs)
        self.pool2 = Pool(c2, c2, rngs=rngs) if stride == 4 else None
        self.hourglass = Hourglass(c2, hourglass_channels, grid // stride, rngs=rngs)
        self.res2 = ResBlock(c2, channels, rngs=rngs)

    def stem_conv(self, voxels: jax.Array) -> jax.Array:
        """The CoordConv stem's conv5 on [occupancy, x, y, z], with its bias (before the norm).

        The occupancy is convolved per sample; the coordinate channels, the same for every
        sample, once in closed form (`coord_conv3d_same`) and broadcast.

        Args:
          voxels: (B, G, G, G) occupancy.

        Returns:
          (B, G, G, G, C/4) float32.
        """
        dtype = self.stem.conv.compute_dtype
        w = self.stem.conv.kernel[...]  # (5, 5, 5, 1 + 3, C/4)
        v, wv, wc = in_compute_dtype(dtype, voxels[..., None], w[..., :1, :], w[..., 1:, :])
        coords = coord_conv3d_same(wc, voxels.shape[1])  # (G, G, G, C/4), as for every sample
        x = (conv3d_same(v, wv, self.stem.conv.conv_form) + coords).astype(jnp.float32)
        return x + self.stem.conv.bias[...]

    def stem_blocks(self, voxels: jax.Array) -> jax.Array:
        """`space_to_depth(self.stem_conv(voxels))`, convolved on the G/2 grid in 2x2x2 blocks
        (`blocked_kernel`); on CPU 2.8x faster than the thin convolution on the full grid.

        voxels (B, G, G, G) -> (B, G/2, G/2, G/2, 8 C/4).
        """
        conv = self.stem.conv
        w = conv.kernel[...]  # (5, 5, 5, 1 + 3, C/4)
        blocks = space_to_depth(voxels[..., None])  # (B, G/2, G/2, G/2, 8)
        v, wv, wc = in_compute_dtype(conv.compute_dtype, blocks, w[..., :1, :], w[..., 1:, :])
        coords = space_to_depth(coord_conv3d_same(wc, voxels.shape[1])[None])
        x = conv3d_same(v, blocked_kernel(wv), conv.conv_form).astype(jnp.float32) + coords
        return x + jnp.tile(conv.bias[...], 8)

    def stem_and_pool(self, voxels: jax.Array) -> jax.Array:
        """The stem (conv5 + GroupNorm + LeakyReLU) and the first strided pool: in 2x2x2 blocks
        where convolutions run in 2D (`stem_blocks`, `Pool.on_blocks`), else on the full grid.

        voxels (B, G, G, G) -> (B, G/2, G/2, G/2, C/4).
        """
        if uses_cpu_rewrites(self.stem.conv.conv_form):
            return self.pool1.on_blocks(
                norm_act_on_blocks(self.stem.norm, self.stem_blocks(voxels))
            )
        return self.pool1(nnx.leaky_relu(self.stem.norm(self.stem_conv(voxels)), LEAK))

    def __call__(self, voxels: jax.Array) -> jax.Array:
        x = self.res1(self.stem_and_pool(voxels))
        if self.pool2 is not None:
            x = self.pool2(x)
        return self.res2(self.hourglass(x))
