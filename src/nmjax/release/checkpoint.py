"""PyTorch's zip checkpoint and the release's opt.pickle read into NumPy, without PyTorch.

A checkpoint is a zip archive with one top folder holding data.pkl (the pickled state dict,
whose tensors name their storages by a persistent id) and one raw file per storage under data/
(shared/release/README.md). It is read by nmjax's restricted unpickler
(`nmjax.data.restricted_pickle`) admitting only what a state dict is made of: the ordered dict,
the tensor-rebuild function and the storage types (`STATE_DICT_GLOBALS`). Anything else in the
pickle is refused before it is built, so reading a checkpoint can never run code. `read_options`
reads opt.pickle admitting only `argparse.Namespace`.
"""

from __future__ import annotations

import argparse
import collections
import hashlib
import io
import pickle
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from nmjax.data.restricted_pickle import RefusedGlobal, RestrictedUnpickler

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


# The globals of a state dict: the ordered dict, the tensor-rebuild function, the storage types.
STATE_DICT_GLOBALS = {
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor,
    **{("torch", name): _StorageType(name) for name in STORAGE_TYPES},
}
OPTIONS_GLOBALS = {("argparse", "Namespace"): argparse.Namespace}  # opt.pickle's one class


def _storage_loader(
    load_storage: Callable[[_StorageType, str, int], _Storage],
) -> Callable[[Any], _Storage]:
    """The persistent-id hook of data.pkl: each storage read from the zip once, by its key."""
    storages: dict[str, _Storage] = {}

    def persistent_load(pid: Any) -> _Storage:
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
        if key not in storages:
            storages[key] = load_storage(pid[1], key, pid[4])
        return storages[key]

    return persistent_load


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
        state = RestrictedUnpickler(
            archive.read(pickles[0]),
            STATE_DICT_GLOBALS,
            persistent_load=_storage_loader(load_storage),
        ).load()
    except RefusedGlobal as err:
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
        options = RestrictedUnpickler(data, OPTIONS_GLOBALS).load()
    except RefusedGlobal as err:
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
