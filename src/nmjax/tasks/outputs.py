"""The files the task commands write, one format each with its name, writer and reader here, and
what kind of folder a path is (`folder_kind`), the one rule `nmjax view` and `nmjax export` share.

- `nmjax generate`: generate.npz, with --voxels voxels.npz (`write_generate`, `read_generate`);
- `nmjax interpolate`: interpolate.npz, one array per method of `INTERPOLATION_METHODS`
  (`write_interpolate`, `read_interpolate`);
- `nmjax retarget`: retarget.npz and the posed target meshes frame_XXXX.obj (`write_retarget`;
  `read_retarget_arrays` the .npz, `read_retarget` the whole folder).

Each .npz also holds the rig, `rig_arrays` of the phase-1 run ("frame_rate", "up_axis", "keep":
what `nmjax export` needs beside the motion), given to every writer and read back with
`rig_format`, which gives the defaults of files written before they held it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from nmjax import atomic, run_folder

GENERATE_FILE = "generate.npz"
GENERATE_VOXELS_FILE = "voxels.npz"  # beside it with `nmjax generate --voxels`
INTERPOLATE_FILE = "interpolate.npz"
RETARGET_FILE = "retarget.npz"  # the keypoints and joints of a `run_retarget` output folder
RETARGET_FRAME = "frame_{:04d}.obj"  # its posed target meshes, one per frame
TASK_FILES = {"generate": GENERATE_FILE, "interpolate": INTERPOLATE_FILE, "retarget": RETARGET_FILE}
# The interpolation methods (`Interpolators`), in the order every table and picture shows them:
# the model, the positional VRNN baseline (only with a run of it), and the two non-generative
# baselines (Sec. 5).
INTERPOLATION_METHODS = ("Ours", "VRNN", "Lerp", "Slerp")
DEFAULT_FRAME_RATE = 30.0  # task outputs written before they stored their run's rate
DEFAULT_UP_AXIS = 2  # ... and its up axis (z, as `nmjax view` assumes for them)


def interpolation_methods(vrnn: bool) -> list[str]:
    """`INTERPOLATION_METHODS` in order, "VRNN" only when a VRNN run is given."""
    return [m for m in INTERPOLATION_METHODS if vrnn or m != "VRNN"]


def folder_kind(folder: str | Path) -> str | None:
    """What `folder` holds: "skel" or "dyn" (a run folder, by its config.json), "generate",
    "interpolate" or "retarget" (a task's output folder, by its file), or None (no folder, or
    none of these). A run folder stays a run whatever task output was written into it."""
    folder = Path(folder)
    if not folder.is_dir():
        return None
    if (folder / run_folder.CONFIG_FILE).is_file():
        return run_folder.run_kind(folder)
    return next((kind for kind, name in TASK_FILES.items() if (folder / name).is_file()), None)


# --- the rig beside every motion -----------------------------------------------------------------


def rig_arrays(skel_run: Path, num_keypoints: int) -> dict[str, np.ndarray]:
    """What `nmjax export` needs beside a task's motions: "frame_rate" and "up_axis" of the
    phase-1 run's sequences and "keep", the (K,) nodes its skeleton keeps."""
    frame_rate, up_axis = run_folder.motion_format(skel_run)
    kept = run_folder.pruned_skeleton(skel_run)
    return {
        "frame_rate": np.float64(frame_rate),
        "up_axis": np.int64(up_axis),
        "keep": np.ones(num_keypoints, bool) if kept is None else kept[1],
    }


def rig_format(arrays: Mapping[str, Any], num_keypoints: int) -> tuple[float, int, np.ndarray]:
    """(frame rate, up axis, keep) of a task output's arrays; defaults for older files."""
    rate = float(arrays["frame_rate"]) if "frame_rate" in arrays else DEFAULT_FRAME_RATE
    up = int(arrays["up_axis"]) if "up_axis" in arrays else DEFAULT_UP_AXIS
    keep = np.asarray(arrays["keep"], bool) if "keep" in arrays else np.ones(num_keypoints, bool)
    return rate, up, keep


def _read_npz(folder: str | Path, kind: str, required: Sequence[str]) -> dict[str, np.ndarray]:
    """Every array of the task output `kind` in `folder`, after checking the `required` ones."""
    path = Path(folder) / TASK_FILES[kind]
    again = f"write it with `nmjax {kind}`"
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found; {again}")
    with np.load(path) as z:
        arrays = {key: z[key] for key in z.files}
    missing = [key for key in required if key not in arrays]
    if missing:
        raise ValueError(f"{path} lacks {', '.join(missing)}; {again}")
    return arrays


# --- generate.npz --------------------------------------------------------------------------------


def write_generate(
    out: Path,
    rig: Mapping[str, np.ndarray],
    *,
    keypoints: np.ndarray,
    observed: np.ndarray,
    observed_frames: np.ndarray,
    names: Sequence[str],
    parents: Sequence[int],
    cond: int,
    voxels: np.ndarray | None = None,
) -> Path:
    """Writes out/generate.npz (and out/voxels.npz with `voxels`); returns the first's path.

    Args:
      rig: `rig_arrays` of the phase-1 run.
      keypoints: (I, S, T_cond + T_gen, K, 4) samples, each starting with the observed frames.
      observed: (I, T, K, 4) the observed frames and the true continuation, padded with its last
        frame where the sequence is shorter.
      observed_frames: (I,) the real frames of `observed`.
      names: the I inputs; parents: (K,) the tree; cond: T_cond.
      voxels: optional (I, S, T, G, G, G) decoded occupancy of every sample (stored as uint8).
    """
    if voxels is not None:
        atomic.save_npz(out / GENERATE_VOXELS_FILE, voxels=np.asarray(voxels).astype(np.uint8))
    path = out / GENERATE_FILE
    atomic.save_npz(
        path,
        keypoints=keypoints,
        observed=observed,
        observed_frames=observed_frames,
        names=np.array(names),
        parents=np.array(parents),
        cond=np.int32(cond),
        **rig,
    )
    return path


def read_generate(folder: str | Path) -> dict[str, np.ndarray]:
    """The arrays of `write_generate` in `folder` (the rig's only where the file has them)."""
    return _read_npz(folder, "generate", ("keypoints", "names", "parents"))


# --- interpolate.npz -----------------------------------------------------------------------------


def write_interpolate(
    out: Path,
    rig: Mapping[str, np.ndarray],
    motions: Mapping[str, np.ndarray],
    *,
    truth: np.ndarray,
    names: Sequence[str],
    parents: Sequence[int],
) -> Path:
    """Writes out/interpolate.npz and returns its path.

    Args:
      rig: `rig_arrays` of the phase-1 run.
      motions: {method: (I, gap + 1, K, 4)} for methods of `INTERPOLATION_METHODS`.
      truth: (I, gap + 1, K, 4) the frames the keyframes were taken from.
      names: the I inputs; parents: (K,) the tree.
    """
    unknown = sorted(set(motions) - set(INTERPOLATION_METHODS))
    if unknown:
        raise ValueError(f"unknown interpolation methods {unknown}; known: {INTERPOLATION_METHODS}")
    path = out / INTERPOLATE_FILE
    atomic.save_npz(
        path,
        truth=truth,
        names=np.array(names),
        parents=np.array(parents),
        **motions,
        **rig,
    )
    return path


def read_interpolate(folder: str | Path) -> dict[str, np.ndarray]:
    """The arrays of `write_interpolate` in `folder`; its methods are the keys of
    `INTERPOLATION_METHODS` it holds (`interpolated_methods`)."""
    return _read_npz(folder, "interpolate", ("truth", "names", "parents"))


def interpolated_methods(arrays: Mapping[str, Any]) -> list[str]:
    """The methods of `INTERPOLATION_METHODS` that the arrays of `read_interpolate` hold."""
    return [m for m in INTERPOLATION_METHODS if m in arrays]


# --- retarget.npz and frame_XXXX.obj -------------------------------------------------------------


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """A triangle mesh as Wavefront .obj text, atomically."""
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    atomic.write_text(path, "\n".join(lines) + "\n")


def write_retarget(
    out: Path,
    rig: Mapping[str, np.ndarray],
    meshes: np.ndarray,
    faces: np.ndarray,
    *,
    source: str,
    source_keypoints: np.ndarray,
    target_keypoints: np.ndarray,
    joints: np.ndarray,
    skin_weights: np.ndarray,
    parents: Sequence[int],
    rotations: np.ndarray,
    rest_rotations: np.ndarray,
    rest_joints: np.ndarray,
    rest_vertices: np.ndarray,
) -> Path:
    """Writes the posed target meshes out/frame_XXXX.obj and out/retarget.npz; returns the .npz.

    Args:
      rig: `rig_arrays` of the phase-1 run.
      meshes: (T, V, 3) the posed target mesh of every frame, in the mesh's units; faces (F, 3).
      source: the source motion's name; source_keypoints (T, K, 4) in its normalised frame.
      target_keypoints: (K, 4) the target mesh's keypoints (its normalised frame).
      joints: (T, K, 3) retargeted joints in the mesh's units; skin_weights (V, K); parents (K,).
      rotations, rest_rotations, rest_joints, rest_vertices: the rig (`nmjax export`): LBS moves
        joint k's part of the mesh rigidly from its rest transform (rest_rotations (K, 3, 3),
        rest_joints (K, 3)) to its transform at t (rotations (T, K, 3, 3), joints); the rest
        mesh (V, 3).
    """
    faces = np.asarray(faces)
    for t, vertices in enumerate(meshes):
        write_obj(out / RETARGET_FRAME.format(t), vertices, faces)
    path = out / RETARGET_FILE
    atomic.save_npz(
        path,
        source_keypoints=source_keypoints,
        target_keypoints=target_keypoints,
        joints=np.asarray(joints, np.float32),
        skin_weights=skin_weights,
        parents=np.array(parents),
        source=np.array(source),
        rotations=np.asarray(rotations, np.float32),
        rest_rotations=np.asarray(rest_rotations, np.float32),
        rest_joints=np.asarray(rest_joints, np.float32),
        rest_vertices=np.asarray(rest_vertices, np.float32),
        faces=faces.astype(np.int64),
        **rig,
    )
    return path


def read_retarget_arrays(folder: str | Path, required: Sequence[str] = ()) -> dict[str, np.ndarray]:
    """The arrays of retarget.npz in `folder` (`write_retarget`), the `required` ones checked
    (files of older versions lack some of the rig's)."""
    return _read_npz(folder, "retarget", required)


def read_retarget(folder: str | Path) -> dict[str, Any]:
    """A `write_retarget` output folder read back, meshes included.

    Returns:
      {"vertices": (T, V, 3) float32 posed target meshes in the mesh's units, "faces": (F, 3),
      "joints": (T, K, 3) retargeted joints in the mesh's units, "parents": (K,),
      "source_keypoints": (T, K, 4) the source motion in its normalised frame, "source": name}.

    Raises:
      FileNotFoundError: no such folder, or one without retarget.npz or frame meshes (names the
        command that writes them).
      ValueError: frames that disagree with each other or with retarget.npz.
    """
    from nmjax.data.meshes import read_mesh

    folder = Path(folder)
    fix = "write it with `nmjax retarget --run RUN --target MESH --out DIR`"
    if not folder.is_dir():
        raise FileNotFoundError(f"retarget output folder {folder} does not exist; {fix}")
    frames = sorted(folder.glob(RETARGET_FRAME.replace("{:04d}", "[0-9]*")))
    if not (folder / RETARGET_FILE).is_file() or not frames:
        raise FileNotFoundError(
            f"{folder} lacks {RETARGET_FILE} or its {RETARGET_FRAME.format(0)}... meshes; is it "
            f"an unfinished retarget output? {fix}"
        )
    arrays = read_retarget_arrays(folder, ("joints", "parents", "source_keypoints", "source"))
    out = {
        "joints": np.asarray(arrays["joints"], np.float32),
        "parents": np.asarray(arrays["parents"]),
        "source_keypoints": np.asarray(arrays["source_keypoints"], np.float32),
        "source": str(arrays["source"]),
    }
    meshes = [read_mesh(path, fix) for path in frames]
    faces = np.asarray(meshes[0].faces)
    if any(
        m.vertices.shape != meshes[0].vertices.shape or len(m.faces) != len(faces) for m in meshes
    ):
        raise ValueError(f"{folder}: the frame meshes differ in vertices or faces; {fix}")
    if len(meshes) != len(out["joints"]):
        raise ValueError(
            f"{folder}: {len(meshes)} frame meshes but {len(out['joints'])} frames of joints in "
            f"{RETARGET_FILE}; {fix}"
        )
    out["vertices"] = np.stack([np.asarray(m.vertices, np.float32) for m in meshes])
    out["faces"] = faces
    return out
