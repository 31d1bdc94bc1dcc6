"""Files of the kind the authors' release ships, written without PyTorch, for tests/test_release.py.

`write_state_dict` writes a state dict in PyTorch's zip format as torch.save does (protocol-2
data.pkl: an OrderedDict of `torch._utils._rebuild_tensor_v2` records whose storages are
persistent ids, one raw little-endian file per storage); tests/release_fixture holds a file of
the same format written by PyTorch itself. `release_tensors` names and shapes arrays after
shared/release/aist_state_dict.tsv or after a smaller network of the same structure, and
`release_options` writes an opt.pickle.
"""

from __future__ import annotations

import argparse
import json
import pickle
import struct
import zipfile
from pathlib import Path

import numpy as np

# Copies of the description of the authors' checkpoint: every tensor's name, shape, dtype and
# module, in order, and every field of its opt.pickle.
FIXTURE = Path(__file__).parent / "release_fixture"
TSV = FIXTURE / "aist_state_dict.tsv"
OPTIONS_JSON = FIXTURE / "aist_options.json"
STORAGES = {
    np.dtype("float32"): "FloatStorage",
    np.dtype("float64"): "DoubleStorage",
    np.dtype("float16"): "HalfStorage",
    np.dtype("int64"): "LongStorage",
    np.dtype("int32"): "IntStorage",
    np.dtype("uint8"): "ByteStorage",
    np.dtype("bool"): "BoolStorage",
}


def _global(module: str, name: str) -> bytes:
    return b"c" + f"{module}\n{name}\n".encode()


def _text(value: str) -> bytes:
    data = value.encode()
    return b"X" + struct.pack("<I", len(data)) + data


def _int(value: int) -> bytes:
    return b"J" + struct.pack("<i", value)


def _tuple(items) -> bytes:
    return b"(" + b"".join(items) + b"t"


def state_dict_pickle(arrays: dict[str, np.ndarray]) -> bytes:
    """data.pkl of `arrays`: storage i holds array i (C order)."""
    out = [b"\x80\x02", _global("collections", "OrderedDict"), b")R", b"("]
    for key, (name, array) in enumerate(arrays.items()):
        strides = [s // array.itemsize for s in np.zeros(array.shape, array.dtype).strides]
        pid = _tuple(
            [
                _text("storage"),
                _global("torch", STORAGES[array.dtype]),
                _text(str(key)),
                _text("cpu"),
                _int(array.size),
            ]
        )
        args = _tuple(
            [
                pid + b"Q",
                _int(0),
                _tuple(map(_int, array.shape)),
                _tuple(map(_int, strides)),
                b"\x89",
                _global("collections", "OrderedDict") + b")R",
            ]
        )
        out += [_text(name), _global("torch._utils", "_rebuild_tensor_v2"), args, b"R"]
    out += [b"u", b"."]
    return b"".join(out)


def write_state_dict(path: Path, arrays: dict[str, np.ndarray], top: str = "archive") -> Path:
    """`arrays` as PyTorch's zip checkpoint at `path`."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        z.writestr(f"{top}/data.pkl", state_dict_pickle(arrays))
        z.writestr(f"{top}/byteorder", "little")
        for key, array in enumerate(arrays.values()):
            z.writestr(
                f"{top}/data/{key}",
                np.ascontiguousarray(array).astype("<" + array.dtype.str[1:]).tobytes(),
            )
        z.writestr(f"{top}/version", "3\n")
    return path


def release_shapes() -> dict[str, tuple[int, ...]]:
    """{name: shape} of every tensor of the released checkpoint, in its order."""
    rows = TSV.read_text().strip().splitlines()[1:]
    shapes = {}
    for row in rows:
        name, shape, _, _ = row.split("\t")
        shapes[name] = tuple(int(n) for n in shape.split("x"))
    return shapes


def release_options(**changes) -> dict:
    """The release's options (aist_options.json) with `changes`."""
    options = json.loads(OPTIONS_JSON.read_text())
    options.update(changes)
    return options


def write_options(path: Path, options: dict) -> Path:
    """`options` as a pickled argparse.Namespace (the release's opt.pickle)."""
    path.write_bytes(pickle.dumps(argparse.Namespace(**options)))
    return path


def random_tensors(shapes: dict[str, tuple[int, ...]], seed: int = 0) -> dict[str, np.ndarray]:
    """float32 arrays of `shapes`, N(0, 0.05^2) (initial state and offsets N(0, 1))."""
    rng = np.random.default_rng(seed)
    out = {}
    for name, shape in shapes.items():
        scale = 1.0 if name.endswith(("offset_param", "init_kypt_rnn_state")) else 0.05
        out[name] = (rng.standard_normal(shape) * scale).astype(np.float32)
    return out
