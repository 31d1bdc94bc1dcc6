"""Writes the PyTorch checkpoints that tests/test_release.py reads, with PyTorch itself.

    python tests/release_fixture/make_fixture.py      (in an environment with torch and numpy)

- tiny_state_dict.pth: the state dict of a module with the layer kinds of the released network
  (Conv3d, ConvTranspose3d, GroupNorm, Linear, GRUCell, a bare parameter), plus tensors of every
  storage type, a 0-d and an empty tensor, and two views of one storage (a transposed one and a
  row at an offset), saved by torch.save in its zip format;
- tiny_state_dict.npz: the same tensors as NumPy arrays (bfloat16 as float32), for comparison;
- tiny_legacy.pth: a small state dict in the pre-1.6 format (which nmjax refuses).

nmjax never imports torch: this script is run once, by hand, and its outputs are committed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).parent


class Tiny(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv3d(2, 3, 3, padding=1)
        self.up = torch.nn.ConvTranspose3d(3, 2, 2, stride=2)
        self.norm = torch.nn.GroupNorm(1, 3)
        self.linear = torch.nn.Linear(4, 5)
        self.cell = torch.nn.GRUCell(4, 3)
        self.state = torch.nn.Parameter(torch.randn(1, 3))


def main() -> None:
    torch.manual_seed(0)
    state = Tiny().state_dict()
    base = torch.arange(24, dtype=torch.float32).reshape(4, 6)
    state["extra.float64"] = torch.randn(2, 3, dtype=torch.float64)
    state["extra.float16"] = torch.randn(5).half()
    state["extra.bfloat16"] = torch.tensor([1.5, -2.25, 3.0e10]).bfloat16()
    state["extra.int64"] = torch.arange(7)
    state["extra.int32"] = torch.tensor([-3, 4], dtype=torch.int32)
    state["extra.int16"] = torch.tensor([-300, 400], dtype=torch.int16)
    state["extra.int8"] = torch.tensor([-3, 4], dtype=torch.int8)
    state["extra.bool"] = torch.tensor([True, False, True])
    state["extra.uint8"] = torch.tensor([0, 255, 7], dtype=torch.uint8)
    state["extra.scalar"] = torch.tensor(3.5)
    state["extra.empty"] = torch.zeros(0, 4)
    state["extra.transposed"] = base.t()  # strides (1, 6) on base's storage
    state["extra.row"] = base[2]  # offset 12 into the same storage
    torch.save(state, HERE / "tiny_state_dict.pth")
    arrays = {
        name: (t.float() if t.dtype == torch.bfloat16 else t).numpy() for name, t in state.items()
    }
    np.savez(HERE / "tiny_state_dict.npz", **arrays)
    legacy = {"weight": torch.ones(2, 2)}
    torch.save(legacy, HERE / "tiny_legacy.pth", _use_new_zipfile_serialization=False)


if __name__ == "__main__":
    main()
