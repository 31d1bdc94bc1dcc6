"""The authors' released model as two nmjax run folders (`nmjax import-release`), without PyTorch.

The authors' repository ships one trained network, `pretrained/aist/aist_pretrained.pth`, with
the options of its run, `pretrained/aist/opt.pickle`. This module turns the pair into a phase-1
and a phase-2 run folder that every nmjax command reads (`runs`), as if `train-skel` and
`train-dyn` had written them:

- `read_checkpoint`: PyTorch's zip checkpoint (a zip archive with one top folder holding
  data.pkl, the pickled state dict whose tensors name their storages by a persistent id, and one
  raw file per storage under data/) read into NumPy arrays by a restricted unpickler that admits
  only what a state dict is made of: the ordered dict, the tensor-rebuild function and the storage
  types. Anything else in the pickle is refused before it is built, so reading a checkpoint can
  never run code. `read_options` reads opt.pickle admitting only `argparse.Namespace`.
- `configs_from_options`: the two run configurations from the options (grid, K, D_z, D_h, T,
  sample rate, loss weights) and the widths the tensors fix.
- `detector_entries`, `dynamics_entries`: the complete name/layout map from the release's tensor
  names (shared/release/aist_state_dict.tsv) onto the parameters of `KeypointDetector` and
  `Dynamics`, each with its layout conversion; `fill` applies it and refuses a tensor left over,
  a parameter left unfilled, or shapes that disagree, naming them.
- `import_release`: all of it, written atomically (a temporary folder renamed onto DIR).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import datetime
import hashlib
import io
import json
import pickle
import shutil
import zipfile
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

# --- reading PyTorch's zip checkpoint --------------------------------------------------------

# torch.<Name>Storage -> NumPy element type (little-endian unless the archive says otherwise).
# bfloat16 has no NumPy type: its 16 bits are the top half of a float32.
STORAGE_TYPES = {
    "FloatStorage": "f4",
    "DoubleStorage": "f8",
    "HalfStorage": "f2",
    "BFloat16Storage": "u2",
    "LongStorage": "i8",
    "IntStorage": "i4",
    "ShortStorage": "i2",
    "CharStorage": "i1",
    "ByteStorage": "u1",
    "BoolStorage": "?",
}
# The pre-1.6 format pickles this magic number first (pickle protocol 2, a LONG1 of 10 bytes).
LEGACY_MAGIC = (0x1950A86A20F9469CFC6C).to_bytes(10, "little")
RESAVE = "re-save it with a current PyTorch: torch.save(torch.load(OLD), NEW)"
MAX_PICKLE_BYTES = 64 << 20  # data.pkl of a state dict is names and small tuples


class Checkpoint(NamedTuple):
    """A state dict read from a PyTorch zip checkpoint."""

    tensors: dict[str, np.ndarray]  # in the file's order
    sha256: str  # of the whole file
    size: int  # bytes


class _StorageType:
    """torch.<Name>Storage as it appears in the pickle: only its element type is used."""

    def __init__(self, name: str):
        self.name = name


class _Storage(NamedTuple):
    values: np.ndarray  # (numel,) in native byte order
    key: str


def _rebuild_tensor(
    storage: _Storage,
    offset: int,
    size: tuple[int, ...],
    stride: tuple[int, ...],
    requires_grad: bool = False,
    backward_hooks: Any = None,
    metadata: Any = None,
) -> np.ndarray:
    """torch._utils._rebuild_tensor_v2's result as a NumPy array: `size` elements of `storage`
    from `offset` with `stride` (in elements), copied into a C-contiguous array.

    Raises:
      ValueError: arguments that are not those of a tensor, or a view reaching past its storage.
    """
    del requires_grad, backward_hooks, metadata  # nothing a weight array needs
    if (
        not isinstance(storage, _Storage)
        or not isinstance(offset, int)
        or not isinstance(size, tuple)
        or not isinstance(stride, tuple)
        or len(size) != len(stride)
        or not all(isinstance(n, int) and n >= 0 for n in (*size, *stride, offset))
    ):
        raise ValueError("a tensor record with malformed storage, offset, size or stride")
    values = storage.values
    if 0 in size:
        return np.zeros(size, values.dtype)
    if not size and offset < len(values):  # a 0-d tensor (as_strided has no 0-d form)
        return np.array(values[offset])
    last = offset + sum((n - 1) * s for n, s in zip(size, stride, strict=True))
    if last >= len(values):
        raise ValueError(
            f"a tensor of size {size} at offset {offset} reaches element {last} of storage "
            f"{storage.key}, which has {len(values)}"
        )
    view = np.lib.stride_tricks.as_strided(
        values[offset:], shape=size, strides=[s * values.itemsize for s in stride], writeable=False
    )
    return np.ascontiguousarray(view)


class _StateDictUnpickler(pickle.Unpickler):
    """Unpickles data.pkl admitting only the classes of a state dict; storages from the zip."""

    def __init__(self, data: bytes, load_storage: Callable[[_StorageType, str, int], _Storage]):
        super().__init__(io.BytesIO(data))
        self._load_storage = load_storage
        self._storages: dict[str, _Storage] = {}

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) == ("collections", "OrderedDict"):
            return collections.OrderedDict
        if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
            return _rebuild_tensor
        if module == "torch" and name in STORAGE_TYPES:
            return _StorageType(name)
        raise ForbiddenClassError(f"{module}.{name}")

    def persistent_load(self, pid: Any) -> _Storage:
        # ("storage", storage type, key, location, number of elements)
        if not (
            isinstance(pid, tuple)
            and len(pid) == 5
            and pid[0] == "storage"
            and isinstance(pid[1], _StorageType)
            and isinstance(pid[4], int)
        ):
            raise ValueError(f"a storage reference {pid!r:.80} that is not PyTorch's")
        key = str(pid[2])
        if key not in self._storages:
            self._storages[key] = self._load_storage(pid[1], key, pid[4])
        return self._storages[key]


class ForbiddenClassError(ValueError):
    """A pickle names a class or function outside the admitted few."""


def _check_file(path: Path, what: str, fix: str) -> bytes:
    """The bytes of `path`, or FileNotFoundError / ValueError naming it and `fix`."""
    if not path.is_file():
        raise FileNotFoundError(f"{what} {path} not found; {fix}")
    data = path.read_bytes()
    if not data:
        raise ValueError(f"{what} {path} is empty; {fix}")
    return data


def read_checkpoint(path: str | Path) -> Checkpoint:
    """The state dict of a PyTorch zip checkpoint as {name: np.ndarray}, without PyTorch.

    Only `collections.OrderedDict`, `torch._utils._rebuild_tensor_v2` and the `torch.*Storage`
    types are admitted; each tensor is rebuilt from its storage file with its offset, size and
    stride; bfloat16 storages become float32.

    Raises:
      FileNotFoundError: no such file.
      ValueError: the pre-1.6 legacy format, a truncated or damaged archive, a pickle naming any
        other class (nothing of it is built), or a content that is not a state dict; each a single
        line naming the file and the fix.
    """
    path = Path(path)
    fix = "give the authors' pretrained/aist/aist_pretrained.pth"
    data = _check_file(path, "checkpoint", fix)
    digest = hashlib.sha256(data).hexdigest()
    if not zipfile.is_zipfile(io.BytesIO(data)):
        if data[:2] == b"\x80\x02" and LEGACY_MAGIC in data[:16]:
            raise ValueError(
                f"checkpoint {path} is in PyTorch's legacy (pre-1.6) format, which nmjax does not "
                f"read; {RESAVE}"
            )
        if data[:4] == b"PK\x03\x04":
            raise ValueError(
                f"checkpoint {path} is a truncated or damaged zip archive ({len(data)} bytes); "
                f"download it again ({fix})"
            )
        raise ValueError(f"{path} is not a PyTorch zip checkpoint; {fix}")
    try:
        archive = zipfile.ZipFile(io.BytesIO(data))
        tensors = _read_archive(archive, path)
    except zipfile.BadZipFile as err:
        raise ValueError(
            f"checkpoint {path} is a damaged zip archive ({err}); download it again"
        ) from err
    return Checkpoint(tensors, digest, len(data))


def _read_archive(archive: zipfile.ZipFile, path: Path) -> dict[str, np.ndarray]:
    names = archive.namelist()
    pickles = [n for n in names if n.count("/") == 1 and n.endswith("/data.pkl")]
    if len(pickles) != 1:
        raise ValueError(
            f"{path} is a zip archive but not a PyTorch checkpoint (no single <top>/data.pkl); "
            "give the .pth file torch.save wrote"
        )
    top = pickles[0][: -len("data.pkl")]
    order = "<"
    if f"{top}byteorder" in names:
        order = {"little": "<", "big": ">"}.get(archive.read(f"{top}byteorder").decode().strip())
        if order is None:
            raise ValueError(f"{path}: unknown byte order in {top}byteorder")
    info = archive.getinfo(pickles[0])
    if info.file_size > MAX_PICKLE_BYTES:
        raise ValueError(f"{path}: data.pkl of {info.file_size} bytes is not a state dict's")

    def load_storage(kind: _StorageType, key: str, numel: int) -> _Storage:
        entry = f"{top}data/{key}"
        dtype = np.dtype(STORAGE_TYPES[kind.name]).newbyteorder(order)
        if entry not in names:
            raise ValueError(f"{path} lacks the storage file {entry}; the archive is incomplete")
        if archive.getinfo(entry).file_size != numel * dtype.itemsize:
            raise ValueError(
                f"{path}: storage {entry} has {archive.getinfo(entry).file_size} bytes, its "
                f"record says {numel} x {dtype.itemsize}; the archive is damaged"
            )
        values = np.frombuffer(archive.read(entry), dtype).astype(dtype.newbyteorder("="))
        if kind.name == "BFloat16Storage":
            values = (values.astype(np.uint32) << 16).view(np.float32)
        return _Storage(values, key)

    try:
        state = _StateDictUnpickler(archive.read(pickles[0]), load_storage).load()
    except ForbiddenClassError as err:
        raise ValueError(
            f"{path} holds {err}, which a state dict never does; refused without building it "
            "(a checkpoint is read admitting only the ordered dict, the tensor-rebuild function "
            "and the storage types); save the weights alone with torch.save(model.state_dict(), "
            "FILE)"
        ) from None
    except (pickle.UnpicklingError, EOFError, TypeError, IndexError, AttributeError) as err:
        raise ValueError(f"{path}: data.pkl cannot be read ({err}); the file is damaged") from err
    if not isinstance(state, dict) or not all(
        isinstance(k, str) and isinstance(v, np.ndarray) for k, v in state.items()
    ):
        raise ValueError(
            f"{path} holds a {type(state).__name__}, not a state dict of named tensors; save "
            "model.state_dict()"
        )
    return dict(state)


class _OptionsUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        if (module, name) == ("argparse", "Namespace"):
            return argparse.Namespace
        raise ForbiddenClassError(f"{module}.{name}")


def read_options(path: str | Path) -> dict[str, Any]:
    """The fields of a pickled `argparse.Namespace` (the release's opt.pickle) as a dict.

    Only `argparse.Namespace` is admitted; its fields are plain values.

    Raises:
      FileNotFoundError: no such file.
      ValueError: another class in the pickle (refused unbuilt), or not a Namespace.
    """
    path = Path(path)
    data = _check_file(path, "options file", "give the authors' pretrained/aist/opt.pickle")
    try:
        options = _OptionsUnpickler(io.BytesIO(data)).load()
    except ForbiddenClassError as err:
        raise ValueError(
            f"options file {path} holds {err}; refused without building it (opt.pickle holds "
            "one argparse.Namespace); give the authors' pretrained/aist/opt.pickle"
        ) from None
    except (pickle.UnpicklingError, EOFError, TypeError, IndexError, AttributeError) as err:
        raise ValueError(f"options file {path} cannot be read ({err}); it is damaged") from err
    if not isinstance(options, argparse.Namespace):
        raise ValueError(
            f"options file {path} holds a {type(options).__name__}, not an argparse.Namespace"
        )
    return dict(vars(options))


# --- configurations from the options ---------------------------------------------------------

DETECTOR = "kypt_detector."
DYNAMICS = "dyna_module."
# Options that select a network other than the one nmjax implements: {name: the supported value}.
SUPPORTED_OPTIONS = {
    "dyna_module": "HSVRNNBVH",  # rotations + forward kinematics ("nm")
    "transition_type": "dl",
    "keypoints_graph": "affinity_params",
    "affinity_ver": 3,  # softmax over the K - 1 others (Eq. 12)
    "const_intensity": 3,  # the spatio-temporal heatmap of the temporal mean (Eq. 6)
    "input_dim": 3,
    "fixed_sigma": 1,
    "gaussian_cat_type": "none",
    "is_binarized": 1,  # occupancy voxels
}
GRAPH_LOSS_VERSIONS = {0: True, 1: False}  # graph_loss_ver -> LossWeights.intensity_weighted
POSTERIOR_SAMPLES = 10  # the release's SAMPLE_NUM, best of S in training and generation


def _option(options: Mapping[str, Any], name: str) -> Any:
    if name not in options:
        raise ValueError(
            f"the options lack {name!r}; give the opt.pickle saved with the checkpoint"
        )
    return options[name]


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


def configs_from_options(options: Mapping[str, Any], widths: Widths, run: str | Path) -> tuple:
    """(SkelTrainConfig, DynTrainConfig) of the released run, for run folders under `run`.

    From the options: the dataset (its nmjax preset supplies the phase-1 crop length and epochs,
    as the release's dataset/config.py does), grid G, K, sigma_g, the N affinities, the sample
    rate, the phase-1 loss weights (complexity = the release's sparsity_const_weight, the term
    its code calls the paper's complexity loss), D_z, D_h, the phase-2 crop T = Ttot, batch,
    epochs, learning rate, KL weight and seed (the phase-2 preset supplies the rest of the
    release's recipe: Adam restarted every epoch, no clipping).

    Raises:
      ValueError: an option that selects a network nmjax does not implement, a missing option,
        or a dataset nmjax does not know.
    """
    from nmjax.config import (
        DynamicsConfig,
        dataset_spec,
        dyn_preset,
        replace_fields,
        skel_preset,
    )

    for name, value in SUPPORTED_OPTIONS.items():
        if _option(options, name) != value:
            raise ValueError(
                f"the options set {name}={options[name]!r}; nmjax implements the released "
                f"network with {name}={value!r} (pretrained/aist/opt.pickle)"
            )
    version = _option(options, "graph_loss_ver")
    if version not in GRAPH_LOSS_VERSIONS:
        raise ValueError(f"the options set graph_loss_ver={version!r}; nmjax has versions 0 and 1")
    dataset = str(_option(options, "dataset"))
    dataset_spec(dataset)
    run = Path(run)
    skel = skel_preset(dataset, "default")
    grid = int(_option(options, "grid_size"))
    data = dataclasses.replace(
        skel.data, grid=grid, sample_rate=int(_option(options, "sample_rate"))
    )
    model = dataclasses.replace(
        skel.model,
        grid=grid,
        num_keypoints=int(_option(options, "nkeypoints")),
        channels=widths.channels,
        hourglass_channels=widths.hourglass,
        sigma_g=float(_option(options, "gaussian_sigma")),
        num_affinity=int(_option(options, "nneighbor")),
    )
    weights = dataclasses.replace(
        skel.weights,
        recon=float(_option(options, "recon_weight")),
        sparse=float(_option(options, "sparse_weight")),
        sep=float(_option(options, "sep_weight")),
        vol=float(_option(options, "vol_reg_weight")),
        local=float(_option(options, "local_const_weight")),
        time=float(_option(options, "time_const_weight")),
        complex=float(_option(options, "sparsity_const_weight")),
        traj=float(_option(options, "graph_traj_weight")),
        sep_sigma=float(_option(options, "sep_sigma")),
        intensity_weighted=GRAPH_LOSS_VERSIONS[version],
    )
    seed = int(_option(options, "seed"))
    learning_rate = float(_option(options, "lrate"))
    skel = replace_fields(
        skel,
        data=data,
        model=model,
        weights=weights,
        learning_rate=learning_rate,
        seed=seed,
        run=str(run / "skel"),
    )
    dyn = replace_fields(
        dyn_preset(dataset, "default"),
        skel_run=str(run / "skel"),
        model=DynamicsConfig(
            model="nm",
            latent=int(_option(options, "nlatent_kypt")),
            hidden=int(_option(options, "nhidden_kypt")),
            mlp=widths.mlp,
            posterior_samples=POSTERIOR_SAMPLES,
        ),
        frames=int(_option(options, "Ttot")),
        batch_size=int(_option(options, "nbatch")),
        epochs=int(_option(options, "nepoch")),
        learning_rate=learning_rate,
        clip_norm=0.0,  # its clip_grad_norm_ runs on gradients already applied (DESIGN 6b)
        kl_weight=float(_option(options, "kl_kypt_weight")),
        seed=seed,
        run=str(run / "dyn"),
    )
    return skel, dyn


# --- the name/layout map ---------------------------------------------------------------------


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


def _names(items: Iterable[Any], limit: int = 6) -> str:
    items = [".".join(map(str, i)) if isinstance(i, tuple) else str(i) for i in items]
    more = f" and {len(items) - limit} more" if len(items) > limit else ""
    return ", ".join(items[:limit]) + more


def fill(model: Any, entries: list[Entry], tensors: Mapping[str, np.ndarray], what: str) -> set:
    """Writes the converted release tensors into every variable of `model` (nnx.state: the
    parameters and the frozen buffers); returns the names of the tensors used.

    Raises:
      ValueError: one line naming the tensors the map needs but the checkpoint lacks, the
        variables no entry fills, or every tensor whose shape is not the one the variable needs
        (both shapes named).
    """
    import jax.numpy as jnp
    from flax import nnx

    state = nnx.state(model)
    variables = dict(nnx.to_flat_state(state))
    absent = sorted({s for e in entries for s in e.sources if s not in tensors})
    unmapped = [p for p in variables if p not in {e.target for e in entries}]
    if absent or unmapped:
        parts = [f"the checkpoint lacks {_names(absent)}"] if absent else []
        parts += [f"no tensor fills {what}'s {_names(unmapped)}"] if unmapped else []
        raise ValueError(f"{'; '.join(parts)}: it is not the network of these options")
    mismatched, values = [], {}
    for entry in entries:
        if entry.target not in variables:
            raise ValueError(f"{what} has no variable {_names([entry.target])} (name map)")
        shape = tuple(variables[entry.target].shape)
        wanted = entry.layout.release_shapes(shape)
        arrays = [tensors[s] for s in entry.sources]
        bad = [
            f"{s} has shape {a.shape}, {what}'s {_names([entry.target])} {shape} needs {w}"
            for s, a, w in zip(entry.sources, arrays, wanted, strict=True)
            if a.shape != w
        ]
        if bad:
            mismatched += bad
            continue
        values[entry.target] = np.asarray(entry.layout.convert(*arrays), np.float32)
    if mismatched:
        more = f" (and {len(mismatched) - 3} more)" if len(mismatched) > 3 else ""
        raise ValueError(
            f"shapes disagree: {'; '.join(mismatched[:3])}{more}: the options do not describe "
            "this checkpoint; give the opt.pickle saved with it"
        )
    for path, value in values.items():
        variables[path].set_value(jnp.asarray(value))
    nnx.update(model, state)
    return {s for e in entries for s in e.sources}


def check_all_used(tensors: Mapping[str, np.ndarray], used: set) -> None:
    """Raises ValueError naming every tensor of the checkpoint that no entry consumed."""
    left = [name for name in tensors if name not in used]
    if left:
        raise ValueError(
            f"the checkpoint has {len(left)} tensor(s) nmjax's networks have no place for: "
            f"{_names(left)}; it is not the released Neural Marionette network"
        )


def build_networks(tensors: Mapping[str, np.ndarray], skel_cfg: Any, dyn_cfg: Any) -> tuple:
    """(detector, dynamics, skeleton) of the release: both networks built from the
    configurations and filled from `tensors`; the skeleton (Algorithm 1 on the imported
    affinity) is the dynamics model's tree.

    Raises:
      ValueError: as `fill` and `check_all_used`.
    """
    from flax import nnx

    from nmjax.models.detector import KeypointDetector
    from nmjax.models.dynamics import Dynamics
    from nmjax.skeleton import DEFAULT_NEIGHBORS, extract_skeleton

    detector = KeypointDetector(skel_cfg.model, rngs=nnx.Rngs(skel_cfg.seed))
    used = fill(detector, detector_entries(detector), tensors, "the detector")
    skeleton = extract_skeleton(np.asarray(detector.affinity()), DEFAULT_NEIGHBORS)
    # Built abstractly (no initialisation to compute): `fill` gives every variable its value.
    dynamics = nnx.eval_shape(
        lambda: Dynamics(dyn_cfg.model, skeleton.parents, skeleton.order, rngs=nnx.Rngs(0))
    )
    used |= fill(dynamics, dynamics_entries(dynamics), tensors, "the dynamics model")
    check_all_used(tensors, used)
    return detector, dynamics, skeleton


# --- writing the two run folders ---------------------------------------------------------------

PROVENANCE_FILE = "release.json"
DEMO_SOURCE = "data/demo/source/gHO_sBM_cAll_d20_mHO1_ch05.npy"  # in the authors' repository


def import_record(checkpoint: Path, ckpt: Checkpoint, options_path: Path, options: Mapping) -> dict:
    """What release.json records beside the provenance stamp (`nmjax.provenance`: the nmjax
    commit and working tree, date, command, machine, versions): the checkpoint (path, bytes,
    sha256, tensors, values) and the options as read."""
    return {
        "checkpoint": str(checkpoint.resolve()),
        "sha256": ckpt.sha256,
        "bytes": ckpt.size,
        "tensors": len(ckpt.tensors),
        "values": int(sum(a.size for a in ckpt.tensors.values())),
        "options_file": str(options_path.resolve()),
        "options": json.loads(json.dumps(dict(options), default=repr)),
    }


def keypoint_motion(detector: Any, cfg: Any, example: str | Path | None) -> tuple:
    """Keypoints (..., T, K, 4) and one voxel frame (G, G, G) of the motion whose statistics go
    into keypoint_stats.npz (the intensities skeleton.json prunes by, the figure's example).

    With `example`, a point-sequence .npy (T, N, >= 3): its first phase-1 crop (T frames every
    `data.sample_rate`-th, one bounding box, `tasks.point_file_keypoints`). Without, the
    evaluation batches of the dataset's test split, the frames `train-skel` measures them on.

    Raises:
      ValueError, FileNotFoundError: an unreadable example or dataset (`check_dataset` first).
    """
    from nmjax import runs

    data = cfg.data
    det = runs.Detector.of(detector, cfg, "")
    if example is not None:
        from nmjax.tasks import point_file_keypoints

        keypoints, voxels = point_file_keypoints(det, example, data.frames, data.sample_rate)
        return keypoints, voxels[0]
    from nmjax.data import pipeline

    batches = pipeline.eval_batches(data, "test", cfg.val_batches, seed=cfg.seed)
    keypoints = np.stack([det.keypoints(b["voxels"]) for b in batches])
    return keypoints, np.asarray(batches[0]["voxels"][0, 0], np.float32)


def check_dataset(data: Any) -> None:
    """Refuses (FileNotFoundError naming both fixes) a dataset whose test split cannot be read,
    when it is to give the keypoint statistics."""
    from nmjax.data.datasets import load_sequences

    try:
        load_sequences(data.name, "test", data.root)
    except (FileNotFoundError, ValueError) as err:
        raise FileNotFoundError(
            f"skeleton.json's keypoint intensities need a motion: give --example POINTS.npy "
            f"(e.g. the authors' {DEMO_SOURCE}) or prepare the {data.name!r} dataset "
            f"({' '.join(str(err).split())})"
        ) from err


def write_phase1_artifacts(run: Path, detector: Any, keypoints: np.ndarray, voxels: Any) -> None:
    """affinity.npy and keypoint_stats.npz as `train.skel.write_artifacts` writes them."""
    from nmjax import atomic, runs

    flat = np.asarray(keypoints, np.float32).reshape(-1, *keypoints.shape[-2:])  # (frames, K, 4)
    atomic.save_npy(run / runs.AFFINITY_FILE, np.asarray(detector.affinity(), np.float32))
    atomic.save_npz(
        run / runs.STATS_FILE,
        intensities=flat[:, :, 3].mean(axis=0),
        rest_positions=flat[:, :, :3].mean(axis=0),
        example_voxels=np.asarray(voxels, np.float32),
        example_keypoints=flat[0],
    )


def _save_run(folder: Path, cfg: Any, model: Any, optimizer: Any) -> None:
    """config.json and the model with a fresh optimizer state as checkpoint 0 (the imported
    parameters before any nmjax step), in the layout the trainers restore."""
    from nmjax import run_folder
    from nmjax.train import checkpoints, optim

    run_folder.prepare_run_dir(folder, resume=False, config=cfg)
    _, state = optim.init_state(model, optimizer)
    with checkpoints.Checkpointer(
        run_folder.checkpoint_dir(folder), cfg.loop.keep_checkpoints
    ) as ckpt:
        ckpt.save(0, state)


def check_run_folder(run: str | Path, overwrite: bool) -> Path:
    """`run` as a Path, after refusing (ValueError) a file, or a folder that holds anything
    unless `overwrite`; `overwrite` replaces only an earlier import (a folder whose skel/ and
    dyn/ hold release.json), never another folder.
    """
    run = Path(run)
    if not run.exists() or (run.is_dir() and not any(run.iterdir())):
        return run
    if not run.is_dir():
        raise ValueError(f"--run {run} is a file; give a folder path")
    if not overwrite:
        raise ValueError(
            f"--run {run} already exists; pass --overwrite to replace it, or choose another folder"
        )
    earlier = all((run / sub / PROVENANCE_FILE).is_file() for sub in ("skel", "dyn"))
    if not earlier or run.resolve() == Path.cwd().resolve():
        raise ValueError(
            f"--run {run} is not a folder `nmjax import-release` wrote, so --overwrite does not "
            "replace it; choose another folder"
        )
    return run


def import_release(
    checkpoint: str | Path,
    options: str | Path,
    run: str | Path,
    *,
    overwrite: bool = False,
    example: str | Path | None = None,
    progress: bool = True,
) -> tuple[Path, Path]:
    """The released model as the run folders `run`/skel (phase 1) and `run`/dyn (phase 2).

    Reads the checkpoint and options (`read_checkpoint`, `read_options`), builds both networks
    from the configurations of the options and fills every parameter (`build_networks`), then
    writes, into a temporary folder beside `run` that is renamed onto it at the end:
    skel/: config.json, checkpoints/0, affinity.npy, keypoint_stats.npz (of `keypoint_motion`),
    skeleton.json and its figure (`runs.extract_run_skeleton`: Algorithm 1 on the imported
    affinity); dyn/: config.json naming skel as its phase-1 run, checkpoints/0; and in both
    release.json (`import_record` and the `nmjax.provenance` stamp). Nothing is left behind when
    a step fails.

    Returns:
      (skel folder, dyn folder).

    Raises:
      FileNotFoundError, ValueError: a missing, truncated, legacy or refused file, options that
        do not match the tensors, an existing `run` without `overwrite`, no motion for the
        keypoint statistics.
    """
    from tqdm import tqdm

    from nmjax import provenance, runs
    from nmjax.tasks import load_point_sequence
    from nmjax.train import dyn, skel

    run = check_run_folder(run, overwrite)
    checkpoint, options = Path(checkpoint), Path(options)
    if example is not None:
        if not Path(example).is_file():
            raise FileNotFoundError(f"--example {example} not found; give a point-sequence .npy")
        load_point_sequence(example)  # refuses another shape before anything is computed
    # Every check that can refuse the inputs comes before the progress bar and the first write.
    opts = read_options(options)
    ckpt = read_checkpoint(checkpoint)
    skel_cfg, dyn_cfg = configs_from_options(opts, network_widths(ckpt.tensors), run)
    if example is None:
        check_dataset(skel_cfg.data)
    detector, dynamics, _ = build_networks(ckpt.tensors, skel_cfg, dyn_cfg)
    stamp = provenance.stamp()  # taken when the work starts, as every results writer does
    record = import_record(checkpoint, ckpt, options, opts)
    record["keypoint_statistics"] = str(example) if example else f"{dyn_cfg.data} test split"
    with tqdm(total=2, desc="import-release", leave=False, disable=not progress) as bar:
        bar.set_postfix_str("keypoint statistics")
        keypoints, voxels = keypoint_motion(detector, skel_cfg, example)
        bar.update()
        bar.set_postfix_str("write")
        target = run.resolve()
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = (
            target.parent / f".{target.name}.import-{datetime.datetime.now().strftime('%H%M%S%f')}"
        )
        try:
            _save_run(tmp / "skel", skel_cfg, detector, skel.StepSettings.of(skel_cfg).optimizer)
            write_phase1_artifacts(tmp / "skel", detector, keypoints, voxels)
            runs.extract_run_skeleton(tmp / "skel")
            _save_run(tmp / "dyn", dyn_cfg, dynamics, dyn.StepSettings.of(dyn_cfg).optimizer)
            for folder in ("skel", "dyn"):
                provenance.write_json(tmp / folder / PROVENANCE_FILE, record, stamp)
            if target.exists():
                shutil.rmtree(target)
            tmp.rename(target)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        bar.update()
    return run / "skel", run / "dyn"
