"""A `Rig` as BVH text (Biovision hierarchy): the skeleton and its motion, no mesh.

HIERARCHY: ROOT / JOINT per joint (named `joint_<k>`), depth first, with OFFSET the rest bone
(the rest pose with every rotation at identity, in the file's axes) and an End Site on every
leaf, a quarter of the leaf's bone further on. Every joint has the six channels

    Xposition Yposition Zposition Zrotation Xrotation Yrotation

in that order: its position in its parent's frame (which replaces OFFSET, as BVH readers take
position channels; for the root, the world position) and its rotation relative to its parent as
intrinsic Euler angles in degrees, R = Rz Rx Ry (`rig.EULER_ORDER`, the order of the CMU
motion-capture files). Why every joint carries a position: see `nmjax.export.rig`. MOTION:
"Frames:", "Frame Time:" (1 / frame rate) and one line per frame with the channels of every
joint in the order the hierarchy lists them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nmjax import atomic
from nmjax.export.rig import Rig, euler_zxy, local_transforms

CHANNELS = "Xposition Yposition Zposition Zrotation Xrotation Yrotation"
END_SITE_FRACTION = 0.25  # End Site offset: this fraction of the leaf's own rest bone


def _number(x: float) -> str:
    """Eight significant digits: files in millimetres and in metres keep the same accuracy."""
    text = f"{x:.8g}"
    return "0" if text == "-0" else text


def _triple(v: np.ndarray) -> str:
    return " ".join(_number(float(x)) for x in v)


def text(rig: Rig) -> str:
    """The BVH file of `rig` as a string."""
    rest_bones = rig.rest_positions - rig.rest_positions[rig.parents]
    rest_bones[0] = rig.rest_positions[0]
    lines = ["HIERARCHY"]
    order: list[int] = []  # joints as the hierarchy lists them: depth first

    def joint(j: int, depth: int) -> None:
        pad = "  " * depth
        order.append(j)
        lines.append(f"{pad}{'ROOT' if j == 0 else 'JOINT'} {rig.names[j]}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {_triple(rest_bones[j])}")
        lines.append(f"{pad}  CHANNELS 6 {CHANNELS}")
        children = rig.children(j)
        for c in children:
            joint(c, depth + 1)
        if not children:
            tip = END_SITE_FRACTION * (rest_bones[j] if j else np.array([0.0, 0.1, 0.0]))
            lines.extend([f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {_triple(tip)}"])
            lines.append(f"{pad}  }}")
        lines.append(f"{pad}}}")

    joint(0, 0)
    local_rot, local_trans = local_transforms(rig.positions, rig.rotations, rig.parents)
    angles = euler_zxy(local_rot)  # (T, J, 3)
    # Equal rotations, smoother curves: no 360-degree jumps between consecutive frames.
    angles = np.unwrap(angles, period=360.0, axis=0)
    lines += ["MOTION", f"Frames: {rig.num_frames}", f"Frame Time: {_number(1.0 / rig.frame_rate)}"]
    channels = np.concatenate([local_trans, angles], axis=-1)[:, order]  # (T, J, 6)
    lines += [_triple(frame.reshape(-1)) for frame in channels]
    return "\n".join(lines) + "\n"


def write(rig: Rig, path: str | Path) -> Path:
    """Writes `rig`'s skeleton and motion as a BVH file, atomically (a mesh is left out)."""
    atomic.write_text(path, text(rig))
    return Path(path)
