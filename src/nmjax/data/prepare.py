"""`nmjax prepare-data`: write a dataset in the nmjax layout (see `nmjax.data.layout`).

    nmjax prepare-data --data synth-hand [--sequences N] [--frames N] [--seed S]
    nmjax prepare-data --data dfaust --from RAW_DIR [--root DIR] [--points 20000]

Synthetic names call `nmjax.data.synthetic.generate`. Real names convert raw mesh sequences:
`RAW_DIR/<seq>/` holds one mesh per frame (.obj / .ply / .off, ordered by name with numbers
compared as numbers, so frame_2 < frame_10) and optionally `joints.npy` (T, J, 3); every frame
becomes `--points` points sampled area-uniformly from its surface (trimesh, seeded per frame).
The train/test split comes from `RAW_DIR/split.json` when present, else the deterministic 9:1
split by frame count. Every file is written atomically and `meta.json` last, so an interrupted run
never leaves a dataset that loads as complete.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np

from nmjax.config import DATASETS
from nmjax.data.layout import (
    JOINT_FILE_PATTERNS,
    SPLITS,
    read_split_file,
    split_by_frames,
    write_index,
    write_sequence,
)

MESH_SUFFIXES = (".obj", ".ply", ".off")
DEFAULT_POINTS = 20_000


def natural_key(path: Path) -> list:
    """Sort key comparing digit runs as numbers: frame_2 before frame_10."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


def find_sequences(source: Path) -> dict[str, list[Path]]:
    """Sequence name -> its mesh frames in order, for every sub-folder of `source` with meshes."""
    if not source.is_dir():
        raise FileNotFoundError(
            f"--from {source}: no such folder; it should hold one folder of mesh frames "
            f"({'/'.join(MESH_SUFFIXES)}) per sequence"
        )
    sequences = {}
    for folder in sorted(p for p in source.iterdir() if p.is_dir()):
        frames = sorted(
            (p for p in folder.iterdir() if p.suffix.lower() in MESH_SUFFIXES), key=natural_key
        )
        if frames:
            sequences[folder.name] = frames
    if not sequences:
        raise FileNotFoundError(
            f"--from {source}: no sub-folder holds {'/'.join(MESH_SUFFIXES)} frames; expected "
            f"{source}/<sequence>/<frame>.obj"
        )
    return sequences


def sample_frame(path: Path, points: int, seed: int) -> np.ndarray:
    """(points, 3) float32 points sampled area-uniformly on the surface of the mesh at `path`."""
    import trimesh  # lazy: keeps `nmjax --help` fast

    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as err:  # trimesh raises many types for malformed files
        raise ValueError(f"{path}: cannot read the mesh ({err})") from err
    if len(mesh.faces) == 0 or not mesh.area > 0:
        raise ValueError(f"{path}: mesh has no surface (faces: {len(mesh.faces)}) to sample from")
    sampled, _ = trimesh.sample.sample_surface(mesh, points, seed=seed)
    sampled = np.asarray(sampled, dtype=np.float32)
    if not np.isfinite(sampled).all():
        raise ValueError(f"{path}: mesh vertices contain NaN or inf")
    return sampled


def _read_raw_joints(path: Path, num_frames: int) -> np.ndarray:
    joints = np.load(path, allow_pickle=False)
    if joints.ndim != 3 or joints.shape[-1] != 3 or joints.shape[0] != num_frames:
        raise ValueError(
            f"{path}: joints must have shape (T, J, 3) with T = {num_frames} mesh frames, "
            f"got {joints.shape}"
        )
    if not np.isfinite(joints).all():
        raise ValueError(f"{path}: joints contain NaN or inf")
    return joints.astype(np.float32)


def clear_dataset(root: Path) -> None:
    """Removes a previous dataset's files (only the nmjax layout, nothing else) from `root`."""
    for split in SPLITS:
        for sub in ("vertices", "joints"):
            if (root / split / sub).is_dir():
                shutil.rmtree(root / split / sub)
    for name in ("meta.json", "split.json"):
        (root / name).unlink(missing_ok=True)


def prepare_meshes(
    name: str,
    source: Path,
    root: Path,
    *,
    points: int = DEFAULT_POINTS,
    seed: int = 0,
    max_sequences: int | None = None,
    max_frames: int | None = None,
) -> Path:
    """Converts raw mesh sequences under `source` into the prepared layout under `root`.

    Returns:
      `root`.
    """
    from tqdm import tqdm

    sequences = find_sequences(source)
    names = list(sequences)[:max_sequences]
    frames = {seq: sequences[seq][:max_frames] for seq in names}
    short = [seq for seq in names if len(frames[seq]) < 2]
    if short:
        raise ValueError(f"--from {source}: sequences with fewer than 2 frames: {short[:5]}")
    split_file = source / "split.json"
    if split_file.is_file():
        split = read_split_file(split_file)
        split = {s: [seq for seq in split[s] if seq in frames] for s in SPLITS}
        unlisted = sorted(set(names) - set(split["train"]) - set(split["test"]))
        if unlisted:
            raise ValueError(f"{split_file}: sequences in neither split: {unlisted[:5]}")
    else:
        split = split_by_frames({seq: len(frames[seq]) for seq in names})
    pattern = JOINT_FILE_PATTERNS[name]
    total = sum(len(f) for f in frames.values())
    # disable=None: no bar when stderr is not a terminal (logs, tests), so errors stay one line
    with tqdm(total=total, unit="frame", desc=f"prepare {name}", disable=None) as bar:
        for split_name in SPLITS:
            for seq in split[split_name]:
                paths = frames[seq]
                bar.set_postfix_str(seq)
                # Seeds differ per sequence and frame; the same seed gives the same bytes.
                base = np.random.SeedSequence([seed, names.index(seq)])
                seeds = base.generate_state(len(paths))
                vertices = np.empty((len(paths), points, 3), dtype=np.float32)
                for t, path in enumerate(paths):
                    vertices[t] = sample_frame(path, points, int(seeds[t]))
                    bar.update(1)
                raw_joints, joints = source / seq / "joints.npy", None
                if raw_joints.is_file():
                    joints = _read_raw_joints(raw_joints, len(sequences[seq]))[: len(paths)]
                write_sequence(
                    root, split_name, seq, joint_file=pattern, joints=joints, vertices=vertices
                )
    meta = {}
    if (source / "meta.json").is_file():
        meta = json.loads((source / "meta.json").read_text())
    meta.update(
        name=name,
        sample_rate=DATASETS[name].sample_rate,
        points=points,
        seed=seed,
        source=str(source),
        frames={seq: len(frames[seq]) for seq in names},
    )
    write_index(root, split, meta)
    return root
