"""The name/layout map: the release's tensor names and shapes (shared/release/
aist_state_dict.tsv) onto the parameters of `KeypointDetector` and `Dynamics`.

Each `Entry` names the release tensors that make one nmjax variable (a path of nnx.state) and
the `Layout` that converts them (PyTorch's documented weight layouts -> channels-last kernels).
`network_widths` reads off the tensors the layer widths the release fixes in its code;
`expected_tensors` gives, for a network, the tensors a checkpoint of it must hold.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import numpy as np

DETECTOR = "kypt_detector."
DYNAMICS = "dyna_module."


@dataclasses.dataclass(frozen=True)
class Widths:
    """Layer widths the release fixes in its code (not in the options), read off the tensors."""

    channels: int  # C of f_feat (128)
    hourglass: tuple[int, ...]  # (32, 48, 72)
    mlp: int  # hidden width of the dynamics MLPs (128)


def network_widths(tensors: Mapping[str, np.ndarray]) -> Widths:
    """C, the hourglass widths and the MLP width from the shapes of the tensors that fix them.

    Raises:
      ValueError: a tensor that every Neural Marionette checkpoint has is missing.
    """
    feat = f"{DETECTOR}vox_to_kypt.extract_features."

    def rows(name: str) -> int:
        if name not in tensors or tensors[name].ndim < 1:
            raise ValueError(
                f"the checkpoint has no tensor {name}: it is not the Neural Marionette network"
            )
        return int(tensors[name].shape[0])

    hourglass = []
    while f"{feat}4.encoder_res{len(hourglass) + 1}.res_branch.0.weight" in tensors:
        hourglass.append(rows(f"{feat}4.encoder_res{len(hourglass) + 1}.res_branch.0.weight"))
    if not hourglass:
        rows(f"{feat}4.encoder_res1.res_branch.0.weight")
    return Widths(
        channels=rows(f"{feat}5.res_branch.0.weight"),
        hourglass=tuple(hourglass),
        mlp=rows(f"{DYNAMICS}extract_post_dist.0.weight"),
    )


class Layout(NamedTuple):
    """How release tensors become one nmjax array: `convert(*tensors)`, and the shapes the
    tensors must have for an nmjax array of a given shape (`release_shapes(shape)`)."""

    name: str
    convert: Callable[..., np.ndarray]
    release_shapes: Callable[[tuple[int, ...]], tuple[tuple[int, ...], ...]]


def conv_kernel(weight: np.ndarray) -> np.ndarray:
    """PyTorch Conv3d weight (out, in, kd, kh, kw) -> channels-last kernel (kd, kh, kw, in, out).

    Both are cross-correlations over the same (x, y, z) axes with the same padding, so the taps
    keep their positions."""
    return np.transpose(weight, (2, 3, 4, 1, 0))


def conv_transpose_kernel(weight: np.ndarray) -> np.ndarray:
    """PyTorch ConvTranspose3d weight (in, out, kd, kh, kw) -> (kd, kh, kw, in, out).

    With kernel = stride = 2 and no padding, PyTorch's output cell 2i + a takes input cell i times
    weight[:, :, a]; `Conv3D(transpose=True)` paints the same block from kernel[a]."""
    return np.transpose(weight, (2, 3, 4, 0, 1))


def linear_kernel(weight: np.ndarray) -> np.ndarray:
    """PyTorch Linear weight (out, in) -> flax kernel (in, out)."""
    return np.transpose(weight)


def pointwise_kernel(weight: np.ndarray) -> np.ndarray:
    """A 1x1x1 Conv3d weight (out, in, 1, 1, 1) -> the (in, out) kernel of an nnx.Linear over
    channels (the detector's heatmap fusion)."""
    return np.transpose(weight.reshape(weight.shape[:2]))


def offset_directions(offset_param: np.ndarray) -> np.ndarray:
    """(K, 3) unit offset directions as the release uses its frozen offset_param:
    p / (||p|| + 1e-10) (its `get_offset`)."""
    norm = np.sqrt(np.sum(np.square(offset_param, dtype=np.float64), axis=-1, keepdims=True))
    return (offset_param / (norm + 1e-10)).astype(np.float32)


SAME = Layout("as is", lambda a: a, lambda s: (s,))
CONV = Layout("Conv3d", conv_kernel, lambda s: ((s[4], s[3], *s[:3]),))
CONV_TRANSPOSE = Layout("ConvTranspose3d", conv_transpose_kernel, lambda s: ((s[3], s[4], *s[:3]),))
LINEAR = Layout("Linear", linear_kernel, lambda s: ((s[1], s[0]),))
POINTWISE = Layout("1x1x1 Conv3d", pointwise_kernel, lambda s: ((s[1], s[0], 1, 1, 1),))
ROW = Layout("(1, H) row", lambda a: a.reshape(-1), lambda s: ((1, *s),))
DIRECTIONS = Layout("normalised offsets", offset_directions, lambda s: (s,))

StatePath = tuple[str | int, ...]


class Entry(NamedTuple):
    """Release tensors `sources` -> the nmjax variable at `target` (a path of nnx.state)."""

    sources: tuple[str, ...]
    target: StatePath
    layout: Layout


def _conv(name: str, path: StatePath, layout: Layout = CONV) -> list[Entry]:
    return [
        Entry((f"{name}.weight",), (*path, "kernel"), layout),
        Entry((f"{name}.bias",), (*path, "bias"), SAME),
    ]


def _norm(name: str, path: StatePath) -> list[Entry]:
    return [
        Entry((f"{name}.weight",), (*path, "scale"), SAME),
        Entry((f"{name}.bias",), (*path, "bias"), SAME),
    ]


def _conv_norm(conv: str, norm: str, path: StatePath) -> list[Entry]:
    """A `ConvNormAct` (conv, norm) from two modules of a release nn.Sequential."""
    return _conv(conv, (*path, "conv")) + _norm(norm, (*path, "norm"))


def _residual(block: Any, name: str, path: StatePath) -> list[Entry]:
    """Res3DBlock: res_branch (0 conv, 1 GN, 3 conv, 4 GN) and skip_con (0 conv, 1 GN)."""
    entries = _conv_norm(f"{name}.res_branch.0", f"{name}.res_branch.1", (*path, "conv1"))
    entries += _conv(f"{name}.res_branch.3", (*path, "conv2"))
    entries += _norm(f"{name}.res_branch.4", (*path, "norm2"))
    if block.skip is not None:
        entries += _conv_norm(f"{name}.skip_con.0", f"{name}.skip_con.1", (*path, "skip"))
    return entries


def _pool(name: str, path: StatePath) -> list[Entry]:
    """Pool3DBlock: stride_conv (0 conv, 1 GN)."""
    return _conv_norm(f"{name}.stride_conv.0", f"{name}.stride_conv.1", (*path, "block"))


def _feature_net(net: Any, name: str, path: StatePath) -> list[Entry]:
    """f_feat: the release's nn.Sequential (0 stem, 1 pool, 2 residual, 3 pool, 4 hourglass, 5
    residual); its hourglass names level i + 1 what `Hourglass` keeps at index i going down and
    at index L - 1 - i coming up."""
    entries = _conv_norm(f"{name}.0.block.0", f"{name}.0.block.1", (*path, "stem"))
    entries += _pool(f"{name}.1", (*path, "pool1"))
    entries += _residual(net.res1, f"{name}.2", (*path, "res1"))
    entries += _pool(f"{name}.3", (*path, "pool2"))
    hg, hg_path = net.hourglass, (*path, "hourglass")
    levels = len(hg.down)
    for i in range(levels):
        level = f"{name}.4.{{}}{i + 1}"
        entries += _pool(level.format("encoder_pool"), (*hg_path, "down", i, "pool"))
        entries += _residual(
            hg.down[i].res, level.format("encoder_res"), (*hg_path, "down", i, "res")
        )
        entries += _residual(hg.skips[i], level.format("skip_res"), (*hg_path, "skips", i))
    for j in range(levels):
        level = f"{name}.4.{{}}{levels - j}"
        entries += _residual(hg.up_res[j], level.format("decoder_res"), (*hg_path, "up_res", j))
        upsample = level.format("decoder_upsample")
        entries += _conv(f"{upsample}.block.0", (*hg_path, "up", j, "conv"), CONV_TRANSPOSE)
        entries += _norm(f"{upsample}.block.1", (*hg_path, "up", j, "norm"))
    entries += _residual(net.res2, f"{name}.5", (*path, "res2"))
    return entries


def detector_entries(model: Any) -> list[Entry]:
    """Every tensor under `kypt_detector.` onto a `KeypointDetector` (heatmap stride 4).

    Raises:
      ValueError: a detector with a pooling level the release does not have.
    """
    if model.features.pool2 is None:
        raise ValueError("the release's detector pools twice (heatmap stride 4)")
    net = f"{DETECTOR}vox_to_kypt."
    entries = [Entry((f"{DETECTOR}affinity_params",), ("affinity_params",), SAME)]
    entries += _feature_net(model.features, f"{net}extract_features", ("features",))
    entries += _feature_net(
        model.st_features, f"{net}extract_spatio_temporal_features", ("st_features",)
    )
    entries += _conv(f"{net}extract_heatmaps_from_features.0", ("heat",))
    entries += _conv(f"{net}extract_spatio_temporal_heatmaps_from_features.0", ("st_heat",))
    # The fusion's two input channels are [frame heatmap, spatio-temporal heatmap] in both.
    entries += _conv(f"{net}propagate_heatmaps.0", ("fuse",), POINTWISE)
    dec = f"{DETECTOR}kypt_to_vox."
    entries += _conv(f"{dec}adjust_combined_representation.0", ("decoder", "inp"))
    seq = f"{dec}decode_voxel_from_combined_representation"
    # Upsample (0, 7), conv (1, 4, 8, 11), GroupNorm (2, 5, 9, 12), LeakyReLU (3, 6, 10, 13).
    for stage, layer, conv in (("up1", 0, 1), ("up1", 1, 4), ("up2", 0, 8), ("up2", 1, 11)):
        entries += _conv_norm(
            f"{seq}.{conv}", f"{seq}.{conv + 1}", ("decoder", stage, "layers", layer)
        )
    entries += _conv(f"{seq}.14", ("decoder", "out"))
    return entries


def dynamics_entries(model: Any) -> list[Entry]:
    """Every tensor under `dyna_module.` (HSVRNNBVH) onto a `Dynamics` of kind "nm".

    The GRU's stacked gates are r, z, n in both, and its two bias vectors are PyTorch's
    (bias_ih, bias_hh), mapped one to one.
    """
    if model.kind != "nm":
        raise ValueError("the release's dynamics module is the 'nm' (rotation) model")
    dyn = DYNAMICS
    entries = [
        Entry((f"{dyn}init_kypt_rnn_state",), ("initial_hidden",), ROW),
        Entry((f"{dyn}offset_param",), ("directions",), DIRECTIONS),
    ]
    mlps = (
        ("extract_post_dist", "posterior"),
        ("extract_prior_dist", "prior"),
        ("root_intensity_decoder", "global_decoder"),
        ("joint_matrix_decoder", "rotation_decoder"),
    )
    for release, ours in mlps:
        entries += _conv(f"{dyn}{release}.0", (ours, "hidden"), LINEAR)
        entries.append(Entry((f"{dyn}{release}.2.weight",), (ours, "out", "kernel"), LINEAR))
        entries.append(Entry((f"{dyn}{release}.2.bias",), (ours, "out", "bias"), SAME))
    cell = f"{dyn}kypt_rnn_cell."
    entries += [
        Entry((f"{cell}weight_ih",), ("rnn", "input_kernel"), LINEAR),
        Entry((f"{cell}weight_hh",), ("rnn", "hidden_kernel"), LINEAR),
        Entry((f"{cell}bias_ih",), ("rnn", "input_bias"), SAME),
        Entry((f"{cell}bias_hh",), ("rnn", "hidden_bias"), SAME),
    ]
    return entries


def expected_tensors(model: Any, entries: list[Entry]) -> dict[str, tuple[int, ...]]:
    """{release name: shape} of the tensors `entries` read for `model`: what a checkpoint of
    the network `model` was built as must hold (the map's side of aist_state_dict.tsv)."""
    from flax import nnx

    variables = dict(nnx.to_flat_state(nnx.state(model)))
    shapes: dict[str, tuple[int, ...]] = {}
    for entry in entries:
        wanted = entry.layout.release_shapes(tuple(variables[entry.target].shape))
        for source, shape in zip(entry.sources, wanted, strict=True):
            shapes[source] = tuple(shape)
    return shapes
