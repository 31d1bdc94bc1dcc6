"""`nmjax export`: the discovered rig and its motion as glTF 2.0 (.glb / .gltf) or BVH (.bvh).

- `sources`: what a run or task output holds, read into a `rig.Rig` (the kept joints, their
  world transforms per frame, the rest pose, a skinned mesh for a retarget output);
- `rig`: the pure math (local transforms, swing rotations, Euler angles, the file's axes);
- `gltf`, `bvh`: the two writers (and the glTF reader `nmjax view` opens a file with).

Every joint is named `joint_<k>`, k its keypoint index in the run's files (skeleton.json,
generate.npz, ...). See docs/export.md for the conventions.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from nmjax.export.rig import Rig, file_axes, transform
from nmjax.export.sources import Options

FORMATS = {".glb": "glTF 2.0 binary", ".gltf": "glTF 2.0 (JSON, buffer embedded)", ".bvh": "BVH"}
UP_AXES = ("x", "y", "z")


def check_output(out: str | Path, overwrite: bool = False) -> str:
    """The format (suffix) of `out`, checked before anything is read.

    Raises:
      ValueError: an unknown suffix.
      FileExistsError: `out` exists and `overwrite` is False.
    """
    out = Path(out)
    suffix = out.suffix.lower()
    if suffix not in FORMATS:
        raise ValueError(
            f"--out {out}: unknown format {suffix or '(no suffix)'!r}; give a file ending in "
            f"{', '.join(FORMATS)}"
        )
    if out.is_dir():
        raise IsADirectoryError(f"--out {out} is a folder; give a file name ending in {suffix}")
    if out.exists() and not overwrite:
        raise FileExistsError(f"--out {out} exists; pass --overwrite to replace it")
    return suffix


def export_run(
    run: str | Path,
    out: str | Path,
    *,
    options: Options | None = None,
    fps: float | None = None,
    up: str | None = None,
    overwrite: bool = False,
) -> tuple[Path, Rig]:
    """Writes the rig and motion of `run` to `out` (format by suffix); returns (out, the rig
    as written, in the file's axes).

    Args:
      run: a run folder or task output (`nmjax.export.sources`).
      out: .glb, .gltf or .bvh; written atomically, so a failure leaves nothing behind.
      options: which motion of `run` (sequence, sample, method, split, seed).
      fps: frames per second; default the run's (`nmjax.config.frame_rate`).
      up: the data's up axis "x", "y" or "z"; default the run's. The file is +Y up.
      overwrite: replace an existing `out`.

    Raises:
      FileNotFoundError, FileExistsError, ValueError: one line naming the input and the fix.
    """
    from nmjax.export import bvh, gltf, sources

    suffix = check_output(out, overwrite)
    if fps is not None and not fps > 0:
        raise ValueError(f"--fps must be > 0, got {fps}")
    rig, up_axis = sources.load(run, options or Options())
    if fps is not None:
        rig = dataclasses.replace(rig, frame_rate=float(fps))
    rig = transform(rig, file_axes(up_axis if up is None else UP_AXES.index(up)))
    writer = bvh.write if suffix == ".bvh" else gltf.write
    return writer(rig, out), rig
