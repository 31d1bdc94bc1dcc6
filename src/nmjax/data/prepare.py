"""`nmjax prepare-data`: write a real dataset in the nmjax layout (see `nmjax.data.layout`).

    nmjax prepare-data --data animals --from DT4D_ROOT/animals [--root DIR] [--points 20000]
    nmjax prepare-data --data dfaust --from DFAUST_ROOT [--subjects 50002,50004]
    nmjax prepare-data --data aist --from AIST_ROOT --body-model SMPL_MALE.pkl
    nmjax prepare-data --data hanco --from HANCO_ROOT --body-model MANO_RIGHT.pkl

`--from` takes a dataset as it is downloaded, where nmjax reads that form:

    animals, dt4d-humanoids   DeformingThings4D `<seq>/<seq>.anime` (`nmjax.data.dt4d`)
    dfaust                    `registrations_m.hdf5`, `registrations_f.hdf5` (`nmjax.data.dfaust`)
    aist                      AIST++ `motions/<seq>.pkl` + the user's SMPL model (`nmjax.data.aist`)
    hanco                     HanCo `meta.json`, `shape/`, `xyz/` + the user's MANO model
                              (`nmjax.data.hanco`)

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

import dataclasses
import re
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from nmjax.data import aist, body_models, dfaust, dt4d, hanco
from nmjax.data.layout import read_meta_file
from nmjax.data.meshes import MESH_SUFFIXES, read_joints, read_mesh, sample_surface
from nmjax.data.streaming import SourceSequence, Summary, select_sequences, write_sequences

DEFAULT_POINTS = 20_000

DT4D_DATASETS = ("animals", "dt4d-humanoids")


class Download(NamedTuple):
    """How a real set comes: the files `--from` holds, where to get them, the `--from` folder,
    and the `--body-model` file it is meshed with (none for sets that come as meshes). `where`
    may take several lines."""

    form: str
    where: str
    source: str
    model: str = ""


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
    "aist": Download(
        "motions/<seq>.pkl, ignore_list.txt (aist_plusplus_final/)",
        "https://google.github.io/aistplusplus_dataset/download.html (annotations)\n"
        "SMPL: https://smpl.is.tue.mpg.de, SMPL 1.1.0 for Python (licensed per user)",
        "AIST_ROOT",
        "SMPL_MALE.pkl",
    ),
    "hanco": Download(
        "meta.json, shape/<sid>/<fid>.json, xyz/<sid>/<fid>.json",
        "https://lmb.informatik.uni-freiburg.de/resources/datasets/HanCo.en.html\n"
        "MANO: https://mano.is.tue.mpg.de, MANO 1.2: MANO_RIGHT.pkl (licensed per user)",
        "HANCO_ROOT",
        "MANO_RIGHT.pkl",
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
    mesh = read_mesh(path)
    return sample_surface(mesh.vertices, mesh.faces, points, seed, str(path))


def mesh_sequences(source: Path) -> list[SourceSequence]:
    """Lists the mesh-frame folders of `source` (`find_sequences`), each with its joints.npy."""
    listed = []
    for seq, paths in find_sequences(source).items():

        def read(points: int, seeds: np.ndarray, seq: str = seq, paths: list = paths) -> dict:
            frames = zip(paths[: len(seeds)], seeds, strict=True)
            vertices = np.stack([sample_frame(path, points, int(s)) for path, s in frames])
            raw_joints, joints = source / seq / "joints.npy", None
            if raw_joints.is_file():
                joints = read_joints(raw_joints, len(paths))[: len(seeds)]
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


# --- AIST++ and HanCo: the download meshed with the user's body model ---------------------------

# The readers of the sets that come as body-model parameters; each module has MODEL_KIND,
# MODEL_SOURCE, FORMAT, PUBLISHED_SPLIT, is_download, list_sequences and dataset_meta.
BODY_MODEL_READERS = {"aist": aist, "hanco": hanco}


class BodyModelSource(NamedTuple):
    """AIST++ / HanCo listed: the sequences, the format's name, whether the published split
    applies, the meta.json entries, and the summary's note on what the reader left out."""

    sequences: list[SourceSequence]
    form: str
    published: bool
    meta: dict
    note: str


def body_model_source(name: str, source: Path, body_model: Path | None) -> BodyModelSource | None:
    """Lists AIST++ / HanCo as downloaded, meshed with the model file `body_model`; None when
    there is no model and `source` is not such a download (mesh folders: `list_source`).

    Raises:
      ValueError: a download without --body-model (the message says where the model is obtained),
        --body-model for another set, a model of the wrong kind, a damaged model or input file.
    """
    reader = BODY_MODEL_READERS.get(name)
    if body_model is None:
        if reader is not None and source.is_dir() and reader.is_download(source):
            raise ValueError(
                f"--data {name} meshes {source} with the {reader.MODEL_KIND} model, which its "
                f"owners license to each user: pass --body-model FILE, {reader.MODEL_SOURCE}"
            )
        return None
    if reader is None:
        raise ValueError(
            f"--body-model is read for --data {' / '.join(BODY_MODEL_READERS)} only, not {name}"
        )
    model = body_models.load_model(body_model)
    body_models.require_kind(model, reader.MODEL_KIND, f"--data {name}", reader.MODEL_SOURCE)
    listed, left_out = reader.list_sequences(source, model)
    shown = ", ".join(left_out[:5]) + (", ..." if len(left_out) > 5 else "")
    note = f"{len(left_out)} {reader.LEFT_OUT}" + (f": {shown}" if left_out else "")
    meta = reader.dataset_meta(model, left_out)
    return BodyModelSource(listed, reader.FORMAT, reader.PUBLISHED_SPLIT, meta, note)


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
    body_model: Path | None = None,
) -> Summary:
    """Converts the raw sequences in `source` into the prepared layout under `root`, one sequence
    at a time (`nmjax.data.streaming.write_sequences`: a rerun skips what is written).

    Every input is listed and checked before `root` is touched; `overwrite` then clears it
    (`nmjax.data.layout.clear_dataset`) instead of continuing what is there. `body_model`: the
    SMPL / MANO file that AIST++ / HanCo are meshed with (`body_model_source`).

    Returns:
      the `Summary` of what was written.
    """
    fitted = body_model_source(name, source, body_model)
    if fitted is not None:
        if subjects is not None:
            raise ValueError(f"--subjects picks D-FAUST subjects; --data {name} takes --sequences")
        listed, form, published, meta, note = fitted
    else:
        listed, form, published = list_source(name, source, subjects=subjects)
        meta, note = {}, None
    chosen = select_sequences(listed, sequences, source)
    if form == "mesh-folders" and (source / "meta.json").is_file():
        # The prepared set's meta.json takes the source's, its tree in nmjax's convention.
        meta = read_meta_file(source / "meta.json")
    meta["format"] = form
    summary = write_sequences(
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
    return summary if note is None else dataclasses.replace(summary, notes=(note,))
