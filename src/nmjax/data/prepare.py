"""`nmjax prepare-data`: write a real dataset in the nmjax layout (see `nmjax.data.layout`).

    nmjax prepare-data --data animals --from DT4D_ROOT/animals [--root DIR] [--points 20000]
    nmjax prepare-data --data dfaust --from DFAUST_ROOT [--subjects 50002,50004]

`--from` takes a dataset as it is downloaded, where nmjax reads that form:

    animals, dt4d-humanoids   DeformingThings4D `<seq>/<seq>.anime` (`nmjax.data.dt4d`)
    dfaust                    `registrations_m.hdf5`, `registrations_f.hdf5` (`nmjax.data.dfaust`)

or, for any real set, one folder of mesh frames per sequence: `RAW_DIR/<seq>/` holds one mesh per
frame (.obj / .ply / .off, ordered by name with numbers compared as numbers, so frame_2 <
frame_10) and optionally `joints.npy` (T, J, 3). Every frame becomes `--points` points sampled
area-uniformly from its surface (trimesh, seeded per sequence name and frame). The split comes
from `RAW_DIR/split.json` when present, else from the published lists for a download that has them
(`nmjax.data.splits`: aist, dfaust, animals), else the deterministic 9:1 split by frame count.
Sequences are written one at a time, each atomically, and `meta.json` last
(`nmjax.data.streaming`): an interrupted run never leaves a dataset that loads as complete, and a
rerun continues it.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from nmjax.data import dfaust, dt4d
from nmjax.data.streaming import (
    SourceSequence,
    Summary,
    sample_surface,
    select_sequences,
    write_sequences,
)

MESH_SUFFIXES = (".obj", ".ply", ".off")
DEFAULT_POINTS = 20_000

DT4D_DATASETS = ("animals", "dt4d-humanoids")


class Download(NamedTuple):
    """How a real set comes: the files `--from` holds, where to get them, the `--from` folder."""

    form: str
    where: str
    source: str


# The sets nmjax reads as they are downloaded (`nmjax prepare-data --help` and the README's table
# show the same). Any real set may also come as mesh folders (`mesh_sequences`).
DOWNLOADS: dict[str, Download] = {
    "dfaust": Download(
        "registrations_m.hdf5, registrations_f.hdf5",
        "https://dfaust.is.tue.mpg.de (after registering: Downloads)",
        "DFAUST_ROOT",
    ),
    "animals": Download(
        "<seq>/<seq>.anime",
        "https://github.com/rabbityl/DeformingThings4D (request form): animals/",
        "DT4D_ROOT/animals",
    ),
    "dt4d-humanoids": Download(
        "<seq>/<seq>.anime",
        "https://github.com/rabbityl/DeformingThings4D (request form): humanoids/",
        "DT4D_ROOT/humanoids",
    ),
}


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
    return sample_surface(mesh.vertices, mesh.faces, points, seed, str(path))


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


def mesh_sequences(source: Path) -> list[SourceSequence]:
    """Lists the mesh-frame folders of `source` (`find_sequences`), each with its joints.npy."""
    listed = []
    for seq, paths in find_sequences(source).items():

        def read(points: int, seeds: np.ndarray, seq: str = seq, paths: list = paths) -> dict:
            frames = zip(paths[: len(seeds)], seeds, strict=True)
            vertices = np.stack([sample_frame(path, points, int(s)) for path, s in frames])
            raw_joints, joints = source / seq / "joints.npy", None
            if raw_joints.is_file():
                joints = _read_raw_joints(raw_joints, len(paths))[: len(seeds)]
            return {"joints": joints, "vertices": vertices}

        listed.append(SourceSequence(seq, len(paths), read))
    return listed


def list_source(
    name: str, source: Path, *, subjects: Sequence[str] | None = None
) -> tuple[list[SourceSequence], str, bool]:
    """Lists the raw sequences of `source` for dataset `name`: the dataset's download as it comes
    when `source` holds one, else one folder of mesh frames per sequence.

    Returns:
      (the sequences, the format's name, whether the published split applies to it).

    Raises:
      FileNotFoundError / ValueError naming `source` or the damaged file.
    """
    if subjects is not None and not (name == "dfaust" and dfaust.registration_files(source)):
        raise ValueError(
            "--subjects picks D-FAUST subjects from registrations_m.hdf5 / registrations_f.hdf5; "
            f"--from {source} holds none (use --sequences NAME,... for mesh folders)"
        )
    if name == "dfaust" and dfaust.registration_files(source):
        return dfaust.registration_sequences(source, subjects), "dfaust-registrations", True
    if name in DT4D_DATASETS and dt4d.anime_files(source):
        return dt4d.anime_sequences(source), "dt4d-anime", True
    try:
        return mesh_sequences(source), "mesh-folders", False
    except FileNotFoundError as err:
        if name in DOWNLOADS and source.is_dir():
            form = DOWNLOADS[name]
            raise FileNotFoundError(f"{err}; or {form.form}, from {form.where}") from err
        raise


def prepare_real(
    name: str,
    source: Path,
    root: Path,
    *,
    points: int = DEFAULT_POINTS,
    seed: int = 0,
    sequences: int | Sequence[str] | None = None,
    max_frames: int | None = None,
    subjects: Sequence[str] | None = None,
    overwrite: bool = False,
) -> Summary:
    """Converts the raw sequences in `source` into the prepared layout under `root`, one sequence
    at a time (`nmjax.data.streaming.write_sequences`: a rerun skips what is written).

    Every input is listed and checked before `root` is touched; `overwrite` then clears it
    (`nmjax.data.layout.clear_dataset`) instead of continuing what is there.

    Returns:
      the `Summary` of what was written.
    """
    listed, form, published = list_source(name, source, subjects=subjects)
    chosen = select_sequences(listed, sequences, source)
    meta = {}
    if form == "mesh-folders" and (source / "meta.json").is_file():
        meta = json.loads((source / "meta.json").read_text())
    meta["format"] = form
    return write_sequences(
        name,
        root,
        chosen,
        source=source,
        points=points,
        seed=seed,
        max_frames=max_frames,
        published=published,
        meta=meta,
        overwrite=overwrite,
    )
