"""How the detector's convolutions and GroupNorm are evaluated: array functions, channels-last.

`nmjax.models.blocks` states what each layer computes; this module holds how, fast, on one
backend. Every fast form here computes the same function as a plain XLA form beside it (the
`*_native` functions), which is what GPU/TPU backends run and what the tests compare against:

- a stride-1 'SAME' convolution (`conv3d_same` against `conv3d_native`): on CPU, XLA's 3D
  convolution is 6.2-13.5x slower forward + backward than the forms below at the cpu preset's
  shapes (case (b) of experiments/results/bench_optimisations_cpu.json), so a float32 3x3x3
  kernel on a grid of side 8 or more is evaluated by Winograd's F(4x4x4, 3x3x3)
  (`winograd_conv3d_valid`: 1/8 of the multiply-adds, as batched matmuls) and any other kernel
  as one 2D convolution over (y, z) with x folded into the batch and the k taps along x stacked
  on the channel axis (`stacked_planes`);
- the 2x2x2 strided convolution ("pool") as a space-to-depth reshape and a matmul, the 2x2x2
  transposed convolution as a matmul and a depth-to-space reshape (every backend);
- the two thin full-grid layers, on CPU, on the half grid in 2x2x2 blocks, where XLA's 2D
  convolutions do well: the CoordConv stem (`coord_conv3d`: the occupancy through
  `blocked_kernel`, the three coordinate channels convolved once, in closed form, on every
  backend) and each convolution after a trilinear upsampling (`upsample_conv3d`: one coarse
  convolution writing the 8 output phases of each block, corrected at the faces);
- GroupNorm's statistics as folded per-channel sums with a hand-written VJP (`group_norm`).

`resolve` holds the only backend check: "auto" (config field `model.conv_form`) is XLA's native
convolution off CPU and the CPU forms on CPU; a named form is taken on every backend (to compare
them). `Evaluation` carries the form and the compute dtype (`model.compute_dtype`) to each layer.
docs/performance.md describes the measurements behind each choice; the timed comparisons of each
fast form with its plain one are experiments/results/bench_optimisations_cpu.json.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from nmjax.keypoints import axis_coords, coord_grid

# --- which form --------------------------------------------------------------------------------

# The forms that run on the CPU layouts (the full-grid rewrites apply to all of them).
CPU_FORMS = ("per_tap", "stacked", "winograd")
CONV_FORMS = ("auto", "native", *CPU_FORMS)
CPU_CONV_FORM = "winograd"  # what "auto" takes on CPU for a float32 3x3x3 kernel
CPU_FALLBACK_FORM = "stacked"  # for other kernels and dtypes, and small grids
WINOGRAD_MIN_SIDE = 8  # "auto": below it, whole tiles of 4^3 outputs waste most of their work
COMPUTE_DTYPES = ("float32", "bfloat16")
# What a `blocks.Conv3D` computes: a stride-1 'SAME' convolution, the 2x2x2 strided one, the
# 2x2x2 transposed one, a 'SAME' convolution after a trilinear 2x upsampling, a CoordConv.
CONV_OPS = ("same", "strided", "transposed", "upsampled", "coords")


def check_conv_form(form: str) -> None:
    """Raises ValueError unless `form` is one of CONV_FORMS (field model.conv_form)."""
    if form not in CONV_FORMS:
        raise ValueError(f"model.conv_form must be one of {', '.join(CONV_FORMS)}, got {form!r}")


def check_compute_dtype(name: str) -> None:
    """Raises ValueError unless `name` is one of COMPUTE_DTYPES (field model.compute_dtype)."""
    if name not in COMPUTE_DTYPES:
        raise ValueError(
            f"model.compute_dtype must be one of {', '.join(COMPUTE_DTYPES)}, got {name!r}"
        )


@dataclasses.dataclass(frozen=True)
class Evaluation:
    """How a layer's convolution is evaluated (hashable: it lives in a model's graphdef).

    Attributes:
      form: one of CONV_FORMS, as `resolve` reads it (config field model.conv_form).
      dtype: the precision of the convolution itself, "float32" or "bfloat16" (field
        model.compute_dtype): input and kernel are cast to it and the result cast back to
        float32, so parameters, normalisation and everything downstream stay float32.
    """

    form: str = "auto"
    dtype: str = "float32"

    def __post_init__(self) -> None:
        check_conv_form(self.form)
        check_compute_dtype(self.dtype)


def resolve(
    form: str, backend: str | None, sides: Sequence[int], kernel_size: int, dtype: jnp.dtype
) -> str:
    """The form that evaluates a stride-1 convolution: "native", "per_tap", "stacked" or
    "winograd".

    Args:
      form: one of CONV_FORMS.
      backend: the JAX backend ("cpu", "gpu", "tpu"); None: `jax.default_backend()`.
      sides: the output grid (X, Y, Z).
      kernel_size: k of the (k, k, k, Ci, Co) kernel.
      dtype: the compute dtype.

    Returns:
      For "auto": "native" off CPU; on CPU `CPU_CONV_FORM` for a float32 3x3x3 kernel on a grid
      of every side >= WINOGRAD_MIN_SIDE, else `CPU_FALLBACK_FORM`. A named form as named, except
      "winograd" where it does not apply (a kernel other than 3x3x3, or not float32: in bfloat16
      the input transform, with coefficients up to 5, would lose the few digits bfloat16 has),
      which takes `CPU_FALLBACK_FORM`.
    """
    check_conv_form(form)
    if form == "auto":
        backend = jax.default_backend() if backend is None else backend
        if backend != "cpu":
            return "native"
        form = CPU_CONV_FORM if min(sides) >= WINOGRAD_MIN_SIDE else CPU_FALLBACK_FORM
    if form == "winograd" and not (kernel_size == 3 and jnp.dtype(dtype) == jnp.float32):
        return CPU_FALLBACK_FORM
    return form


def in_compute_dtype(name: str, *arrays: jax.Array) -> tuple[jax.Array, ...]:
    """`arrays` cast to the compute dtype `name` ("float32" leaves them as they are)."""
    if name == "float32":
        return arrays
    return tuple(a.astype(jnp.dtype(name)) for a in arrays)


# --- a layer's convolution ---------------------------------------------------------------------


def conv3d(
    x: jax.Array, kernel: jax.Array, op: str = "same", evaluation: Evaluation = Evaluation()
) -> jax.Array:
    """The convolution of a `blocks.Conv3D` (no bias), in its fast form: `conv3d_native`'s
    function.

    Args:
      x: (B, X, Y, Z, Ci) input; for "coords" (B, X, X, X, Ci - 3), the coordinate channels
        being the layer's own.
      kernel: (k, k, k, Ci, Co).
      op: one of CONV_OPS: "same" (odd k), "strided" and "transposed" (k = 2), "upsampled"
        (odd k; the input upsampled 2x first), "coords" (odd k).
      evaluation: form and compute dtype.

    Returns:
      float32 (B, X', Y', Z', Co): X' = X for "same" and "coords", X / 2 for "strided", 2 X for
      "transposed" and "upsampled".
    """
    x, kernel = in_compute_dtype(evaluation.dtype, x, kernel)
    form = evaluation.form
    if op == "same":
        y = pointwise(x, kernel) if kernel.shape[0] == 1 else conv3d_same(x, kernel, form)
    elif op == "strided":
        y = strided_conv2(x, kernel)
    elif op == "transposed":
        y = transposed_conv2(x, kernel)
    elif op == "upsampled":
        y = upsample_conv3d(x, kernel, form)
    elif op == "coords":
        y = coord_conv3d(x, kernel, form)
    else:
        raise ValueError(f"conv3d: op must be one of {CONV_OPS}, got {op!r}")
    return y.astype(jnp.float32)


def conv3d_native(x: jax.Array, kernel: jax.Array, op: str = "same") -> jax.Array:
    """The plain form of `conv3d`, float32: XLA's 3D convolution, the input upsampled or the
    coordinates concatenated first where the op says so."""
    if op == "same":
        return _native_same(x, kernel)
    if op == "strided":
        return jax.lax.conv_general_dilated(x, kernel, (2, 2, 2), "VALID", dimension_numbers=_NDHWC)
    if op == "transposed":  # the input dilated by 2, correlated with the flipped kernel
        flipped = kernel[::-1, ::-1, ::-1]
        return jax.lax.conv_general_dilated(
            x, flipped, (1, 1, 1), ((1, 1),) * 3, lhs_dilation=(2, 2, 2), dimension_numbers=_NDHWC
        )
    if op == "upsampled":
        return _native_same(upsample_trilinear(x), kernel)
    if op == "coords":
        coords = jnp.broadcast_to(coord_grid(x.shape[1]), (*x.shape[:-1], 3))
        return _native_same(jnp.concatenate([x, coords.astype(x.dtype)], axis=-1), kernel)
    raise ValueError(f"conv3d_native: op must be one of {CONV_OPS}, got {op!r}")


_NDHWC = ("NDHWC", "DHWIO", "NDHWC")
_NHWC = ("NHWC", "HWIO", "NHWC")


def _native_same(x: jax.Array, kernel: jax.Array) -> jax.Array:
    return jax.lax.conv_general_dilated(x, kernel, (1, 1, 1), "SAME", dimension_numbers=_NDHWC)


def pointwise(x: jax.Array, kernel: jax.Array) -> jax.Array:
    """A 1x1x1 convolution: (..., Ci) with (1, 1, 1, Ci, Co) -> (..., Co), one matmul."""
    return jnp.einsum("...i,io->...o", x, kernel[0, 0, 0])


# --- stride-1 'SAME' convolution ----------------------------------------------------------------


def _check_conv_args(name: str, k: int, form: str) -> None:
    """Raises ValueError unless the kernel size `k` is odd and `form` is one of CONV_FORMS."""
    if k % 2 == 0:
        raise ValueError(f"{name} needs an odd kernel size, got {k}")
    if form not in CONV_FORMS:
        raise ValueError(f"{name}: form must be one of {CONV_FORMS}, got {form!r}")


def conv3d_same(x: jax.Array, kernel: jax.Array, form: str = "auto") -> jax.Array:
    """Stride-1 'SAME' 3D convolution (cross-correlation) of x (B,X,Y,Z,Ci) with (k,k,k,Ci,Co).

    Odd k only. Every form computes `conv3d_native`'s function:
      "native": XLA's 3D convolution.
      "per_tap": 2D convolutions over (Y, Z) with X folded into the batch axis, one per offset a
        along X of the shifted planes x[:, a : a + X] (a fixed loop over kernel taps, not over
        data), summed.
      "stacked": the k shifted planes concatenated on the channel axis into a single 2D
        convolution with a k-times deeper kernel.
      "winograd": Winograd's minimal filtering F(4x4x4, 3x3x3) (`winograd_conv3d_valid`).
      "auto": as `resolve` chooses on this backend.
    """
    k = kernel.shape[0]
    _check_conv_args("conv3d_same", k, form)
    if resolve(form, None, x.shape[1:4], k, kernel.dtype) == "native":
        return _native_same(x, kernel)
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
    form = resolve(form, None, (nx, ny, nz), k, kernel.dtype)
    if form == "winograd":
        return winograd_conv3d_valid(padded, kernel)
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


# With YNNPACK's convolutions switched off (nmjax/__init__.py), XLA's CPU 2D convolution beats
# its 3D convolution: the stem's k=5 convolution as stacked taps is 12.4x faster forward +
# backward at the cpu preset (case (b) of experiments/results/bench_optimisations_cpu.json).
# Stacking the k taps along X on the channel axis (one 2D convolution with a k-times deeper
# kernel) was kept over one 2D convolution per tap and over a k-times wider output (the taps'
# kernels side by side, the results shifted and summed) by the comparisons docs/performance.md
# describes ("CPU convolutions", "GroupNorm and stacked taps"); no results file holds them.
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


# --- Winograd F(4x4x4, 3x3x3) -------------------------------------------------------------------

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


# --- 2x2x2 blocks: the strided and the transposed convolution ------------------------------------


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


def strided_conv2(x: jax.Array, kernel: jax.Array) -> jax.Array:
    """The 2x2x2 convolution of stride 2, (B, X, Y, Z, Ci) with (2, 2, 2, Ci, Co) -> (B, X/2,
    Y/2, Z/2, Co): each output cell sees exactly one 2x2x2 block of the input, one matmul."""
    return space_to_depth(x) @ kernel.reshape(-1, kernel.shape[-1])


def transposed_conv2(x: jax.Array, kernel: jax.Array) -> jax.Array:
    """The 2x2x2 transposed convolution of stride 2, (B, X, Y, Z, Ci) with (2, 2, 2, Ci, Co) ->
    (B, 2X, 2Y, 2Z, Co): each input cell paints its own 2x2x2 block of the output."""
    y = jnp.einsum("...i,abcio->...abco", x, kernel)
    return depth_to_space(y.reshape(*x.shape[:-1], -1))


# --- the full-grid layers on the half grid -------------------------------------------------------

# The detector's layers at the full grid G^3 have 1-8 channels, where every form of XLA's CPU
# convolution spends its time in copies and transposes rather than in arithmetic. Two exact
# rewrites move them to the G/2 grid with 8x the channels, in 2x2x2 blocks (the
# `space_to_depth` layout), which XLA's 2D convolutions handle well:
# - a stride-1 convolution of a thin input equals a k=3 convolution of its blocks with a
#   block-structured kernel (`blocked_kernel`); the stem (1 -> C/4 channels, k=5) costs 1.7x
#   the arithmetic that way, and the stem and first pool run 30x faster forward + backward than
#   on the full grid by XLA's 3D convolution (case (f) of
#   experiments/results/bench_optimisations_cpu.json);
# - a k=3 convolution after a 2x trilinear upsampling equals one k=3 convolution of the coarse
#   input that writes the 8 output phases of each block (`upsample_conv3d_blocks`), with the
#   same arithmetic as the fine convolution and no fine input at all (the decoder's two
#   upsampling stages).
# Both return the fine layout: the norm after them is as fast there as on the blocks, and its
# backward reads the incoming gradient in order.


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


def coord_channels_conv3d(kernel: jax.Array, n: int) -> jax.Array:
    """`conv3d_native(coord_grid(n)[None], kernel)[0]`, (k,k,k,3,Co) -> (n,n,n,Co), in closed
    form.

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


def coord_conv3d(x: jax.Array, kernel: jax.Array, form: str = "auto") -> jax.Array:
    """CoordConv (Liu et al. 2018): the 'SAME' convolution of x with the three coordinate
    channels of its grid appended, `conv3d_native(x, kernel, "coords")`.

    Args:
      x: (B, n, n, n, Ci - 3).
      kernel: (k, k, k, Ci, Co), the last 3 input channels those of the coordinates x, y, z.
      form: as in `conv3d_same`.

    Returns:
      (B, n, n, n, Co).

    The convolution is linear in its input channels: the coordinate channels, the same for
    every sample, are convolved once, in closed form (`coord_channels_conv3d`), and broadcast
    instead of being concatenated to every sample (4x cheaper for the detector's one-channel
    occupancy). Where a CPU form evaluates it, x is convolved on the n/2 grid in 2x2x2 blocks
    (`blocked_kernel`; the comment opening this section says what that was measured at).
    """
    n, k = x.shape[1], kernel.shape[0]
    if x.shape[1:4] != (n, n, n) or kernel.shape[3] != x.shape[-1] + 3:
        raise ValueError(
            f"coord_conv3d: x must be (B, n, n, n, Ci - 3) for a kernel (k, k, k, Ci, Co), got "
            f"{x.shape} and {kernel.shape}"
        )
    w_x, w_coords = kernel[..., :-3, :], kernel[..., -3:, :]
    coords = coord_channels_conv3d(w_coords, n)  # (n, n, n, Co), as for every sample
    blocked = n % 2 == 0 and k <= 5 and resolve(form, None, (n,) * 3, k, x.dtype) != "native"
    if not blocked:
        return conv3d_same(x, w_x, form) + coords
    y = conv3d_same(space_to_depth(x), blocked_kernel(w_x), form)
    return depth_to_space(y.astype(jnp.float32) + space_to_depth(coords[None]))


def upsample_trilinear(x: jax.Array) -> jax.Array:
    """(B, X, Y, Z, C) -> (B, 2X, 2Y, 2Z, C) by trilinear interpolation (half-pixel centres)."""
    b, nx, ny, nz, c = x.shape
    return jax.image.resize(x, (b, 2 * nx, 2 * ny, 2 * nz, c), method="linear")


def upsample_conv3d(x: jax.Array, kernel: jax.Array, form: str = "auto") -> jax.Array:
    """`conv3d_same(upsample_trilinear(x), kernel, form)`: x (B, X, Y, Z, Ci) with (k, k, k,
    Ci, Co) -> (B, 2X, 2Y, 2Z, Co).

    Where a CPU form evaluates it and k = 3, convolved on the coarse grid without forming the
    upsampled one (`upsample_conv3d_blocks`); elsewhere the two steps as written.
    """
    k = kernel.shape[0]
    sides = [2 * s for s in x.shape[1:4]]
    if k != 3 or resolve(form, None, sides, k, kernel.dtype) == "native":
        return conv3d_same(upsample_trilinear(x), kernel, form)
    return depth_to_space(upsample_conv3d_blocks(x, kernel, form))


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
    upsampling (away from the grid's faces; `upsample_conv3d_blocks` corrects those)."""
    if kernel.shape[:3] != (3, 3, 3):
        raise ValueError(f"upsample_conv_kernel needs a 3x3x3 kernel, got {kernel.shape}")
    u = jnp.asarray(_upsample_taps(), kernel.dtype)
    w = jnp.einsum("dqe,frg,hsj,dfhio->egjiqrso", u, u, u, kernel)
    return w.reshape(3, 3, 3, kernel.shape[3], 8 * kernel.shape[4])


def upsample_conv3d_blocks(x: jax.Array, kernel: jax.Array, form: str = "auto") -> jax.Array:
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


# --- GroupNorm ----------------------------------------------------------------------------------


def group_norm_native(
    x: jax.Array, scale: jax.Array, bias: jax.Array, groups: int, eps: float
) -> jax.Array:
    """The plain form of `group_norm`: the group statistics by `jnp.mean`, differentiated by
    autodiff (the function `flax.nnx.GroupNorm` computes)."""
    n, c = x.shape[0], x.shape[-1]
    grouped = x.reshape(n, -1, groups, c // groups)
    mean = jnp.mean(grouped, axis=(1, 3), keepdims=True)
    var = jnp.maximum(jnp.mean(grouped * grouped, axis=(1, 3), keepdims=True) - mean * mean, 0.0)
    normed = (grouped - mean) * jax.lax.rsqrt(var + eps)
    return normed.reshape(x.shape) * scale + bias


def cell_sums(x: jax.Array) -> jax.Array:
    """(N, S, C) -> (N, C): the sum over the S cells of each channel.

    XLA's CPU reduction over a middle axis keeps only the C minor values per row in flight;
    folding up to 64 consecutive cells into the minor axis first (one reduction over S / f rows
    of f C values, then one over f) shortens those rows (docs/performance.md, "GroupNorm and
    stacked taps", describes the change; no results file times it alone), and its float32 sums
    are closer to float64 than a single long reduction.
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
    x: jax.Array, scale: jax.Array, bias: jax.Array, groups: int, eps: float
) -> jax.Array:
    """GroupNorm (Wu & He 2018; the detector's norm, paper Fig. 9) of channels-last x:
    `group_norm_native`'s function.

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
    of the incoming gradient, re-reading the inputs in every one of them). docs/performance.md,
    "GroupNorm and stacked taps", describes the step it came with; no results file times it
    against flax's alone.
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
