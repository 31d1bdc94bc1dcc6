"""`nmjax prepare-data`: write a real dataset in the nmjax layout (see `nmjax.data.layout`).

    nmjax prepare-data --from RAW --root OUT [--up z] [--fps 30] [--units m]   (your capture)
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

or, for any real set and for a user's own capture (no --data: the generic `capture` spec,
`prepare_capture`), one entry per sequence (`raw_sequences`):

- `RAW/<seq>/`, one file a frame, ordered by name with numbers compared as numbers (frame_2 <
  frame_10): meshes (.obj / .ply / .off), or point clouds (a .ply / .obj / .off with vertices
  only, .xyz / .txt with x y z a line, .npy of shape (N, 3)); optionally `joints.npy` (T, J, 3);
- `RAW/<seq>.npy` or `.npz`: the sequence's points as one (T, N, 3) array;
- or RAW itself one folder of frames (no sub-folders of frames, no arrays): one sequence, named
  after the folder.

Every frame becomes `--points` points: a mesh sampled area-uniformly on its surface (trimesh), a
point cloud of N points resampled (`resample_points`: N > P keeps P distinct points drawn at
random, N < P keeps all and draws P - N of them again), each seeded per sequence name and frame.
NaN / inf are refused naming the file, the frame and the vertex. The split comes from
`RAW/split.json` when present (it may name only sequences RAW holds), else from the published
lists for a download that has them (`nmjax.data.splits`: aist, dfaust, animals), else the
deterministic 9:1 split by frame count; a single sequence is cut in two instead, its last 10%
of frames (at least a training crop) the test sequence `<seq>_test`
(`nmjax.data.streaming.hold_out_test`). Sequences are written one at a time, each atomically,
and `meta.json` last (`nmjax.data.streaming`): an interrupted run never leaves a dataset that
loads as complete, and a rerun continues it.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from nmjax.data import aist, body_models, dfaust, dt4d, hanco
from nmjax.data.layout import CAPTURE, capture_meta, read_meta_file
from nmjax.data.meshes import (
    FRAME_SUFFIXES,
    MESH_SUFFIXES,
    POINT_ARRAY_SUFFIXES,
    POINT_SUFFIXES,
    point_array_shape,
    read_frame,
    read_joints,
    read_point_array,
    require_finite,
    sample_surface,
)
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


JOINTS_FILE = "joints.npy"  # a frame folder's ground-truth joints, not a frame
FORMS = ("mesh-folders", "point-folders", "point-arrays")  # the forms any real set may take


def frame_files(folder: Path) -> list[Path]:
    """The frames of one sequence folder in natural order: its .obj / .ply / .off files (meshes,
    or vertices-only point clouds), or, when it has none, its .xyz / .txt / .npy point files
    whose names carry a frame number (frame_003.xyz), so that a readme.txt or the joints.npy
    beside them is no frame. Hidden files are no frames either."""
    files = [p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")]
    meshes = [p for p in files if p.suffix.lower() in MESH_SUFFIXES]
    points = [
        p
        for p in files
        if p.suffix.lower() in POINT_SUFFIXES and p.name != JOINTS_FILE and re.search(r"\d", p.stem)
    ]
    return sorted(meshes or points, key=natural_key)


def find_sequences(source: Path) -> dict[str, list[Path] | Path]:
    """Sequence name -> its frames in order (a sub-folder of `source`, `frame_files`), or the
    one file that holds it (`source/<seq>.npy` or `.npz`, a (T, N, 3) array). A `source` that
    holds neither but frames of its own (.obj / .ply / .off / .xyz / .txt: one folder of frames
    handed over as it is) is one sequence, named after the folder.

    Raises:
      FileNotFoundError: `source` is no folder, or holds neither.
      ValueError: a name that is both a folder and an array file.
    """
    expected = (
        f"expected {source}/<sequence>/<frame>.obj (one mesh or point file a frame: "
        f"{'/'.join(FRAME_SUFFIXES)}) or {source}/<sequence>.npy (T, N, 3)"
    )
    if not source.is_dir():
        raise FileNotFoundError(f"--from {source}: no such folder; {expected}")
    sequences: dict[str, list[Path] | Path] = {}
    for entry in sorted(source.iterdir(), key=natural_key):
        if entry.name.startswith("."):
            continue
        if entry.is_dir() and (frames := frame_files(entry)):
            sequences[entry.name] = frames
    for entry in sorted(source.iterdir(), key=natural_key):
        if entry.is_file() and not entry.name.startswith("."):
            if entry.suffix.lower() in POINT_ARRAY_SUFFIXES:
                if entry.stem in sequences:
                    raise ValueError(
                        f"--from {source}: sequence {entry.stem!r} is both a folder of frames "
                        f"and {entry.name}; keep one"
                    )
                sequences[entry.stem] = entry
    if not sequences:
        # .npy files directly in `source` are (T, N, 3) arrays (above), never frames of it.
        own = [p for p in frame_files(source) if p.suffix.lower() not in POINT_ARRAY_SUFFIXES]
        if own:
            return {source.resolve().name: own}
        raise FileNotFoundError(
            f"--from {source}: no sub-folder holds {'/'.join(FRAME_SUFFIXES)} frames and no "
            f"{'/'.join(POINT_ARRAY_SUFFIXES)} array is there; {expected}"
        )
    return sequences


def resample_points(points: np.ndarray, count: int, seed: int) -> np.ndarray:
    """(count, 3) float32 points of a point-cloud frame (N, 3), seeded by `seed`.

    N = count: as given. N > count: `count` distinct points drawn uniformly (kept in their
    order). N < count: every point once, then count - N more drawn uniformly with replacement
    (the surface is what the capture measured: repeating points adds none).
    """
    n = len(points)
    if n == count:
        return np.asarray(points, np.float32)
    rng = np.random.default_rng(seed)
    if n > count:
        index = np.sort(rng.choice(n, count, replace=False))
    else:
        index = np.concatenate([np.arange(n), rng.integers(0, n, count - n)])
    return np.asarray(points[index], np.float32)


def read_frames(paths: Sequence[Path], points: int, seeds: np.ndarray) -> np.ndarray:
    """(T, points, 3) float32: frame t of `paths` read with seed `seeds[t]`, a mesh sampled
    area-uniformly on its surface (`sample_surface`), a point cloud resampled
    (`resample_points`). A sequence's frames are all meshes or all point clouds.

    Raises:
      ValueError naming the file: unreadable, NaN / inf (the vertex), no surface, or a frame of
        the other kind than the first.
    """
    sampled = np.empty((len(paths), points, 3), np.float32)
    first: tuple[Path, bool] | None = None  # the first frame and whether it is a mesh
    for t, (path, seed) in enumerate(zip(paths, seeds, strict=True)):
        vertices, faces = read_frame(path)
        require_finite(vertices, str(path))
        mesh = len(faces) > 0
        first = first or (path, mesh)
        if first[1] and not mesh:
            raise ValueError(
                f"{path}: mesh has no surface (faces: 0) to sample from, while {first[0].name} is "
                "a mesh; a sequence's frames are all meshes or all point clouds"
            )
        if mesh and not first[1]:
            raise ValueError(
                f"{path} is a mesh ({len(faces)} faces), while {first[0].name} is a point cloud; "
                "a sequence's frames are all meshes or all point clouds"
            )
        if mesh:
            sampled[t] = sample_surface(vertices, faces, points, int(seed), str(path))
        else:
            sampled[t] = resample_points(vertices, points, int(seed))
    return sampled


def folder_sequence(seq: str, paths: list[Path]) -> SourceSequence:
    """A folder of frame files (`read_frames`), with its joints.npy when it has one."""

    def read(points: int, seeds: np.ndarray) -> dict:
        vertices = read_frames(paths[: len(seeds)], points, seeds)
        raw_joints, joints = paths[0].parent / JOINTS_FILE, None
        if raw_joints.is_file():
            joints = read_joints(raw_joints, len(paths))[: len(seeds)]
        return {"joints": joints, "vertices": vertices}

    return SourceSequence(seq, len(paths), read)


def array_sequence(seq: str, path: Path) -> SourceSequence:
    """One (T, N, 3) array file, its frames counted from the header; every frame resampled to
    the points asked for (`resample_points`)."""
    num_frames = point_array_shape(path)[0]

    def read(points: int, seeds: np.ndarray) -> dict:
        frames = read_point_array(path, len(seeds))
        pairs = zip(frames, seeds, strict=True)
        vertices = np.stack([resample_points(x, points, int(s)) for x, s in pairs])
        return {"joints": None, "vertices": vertices}

    return SourceSequence(seq, num_frames, read)


def raw_sequences(source: Path) -> tuple[list[SourceSequence], str]:
    """Lists the sequences of `source` (`find_sequences`): folders of frames and array files.

    Returns:
      (the sequences, the form: "mesh-folders" (.obj / .ply / .off frames), "point-folders"
      (.xyz / .txt / .npy frames), "point-arrays", or those present joined by "+").
    """
    listed, forms = [], set()
    for seq, found in find_sequences(source).items():
        if isinstance(found, Path):
            listed.append(array_sequence(seq, found))
            forms.add("point-arrays")
        else:
            listed.append(folder_sequence(seq, found))
            mesh = found[0].suffix.lower() in MESH_SUFFIXES
            forms.add("mesh-folders" if mesh else "point-folders")
    return listed, "+".join(form for form in FORMS if form in forms)


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
        return (*raw_sequences(source), False)
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
    extra_meta: dict | None = None,
) -> Summary:
    """Converts the raw sequences in `source` into the prepared layout under `root`, one sequence
    at a time (`nmjax.data.streaming.write_sequences`: a rerun skips what is written).

    Every input is listed and checked before `root` is touched; `overwrite` then clears it
    (`nmjax.data.layout.clear_dataset`) instead of continuing what is there. `body_model`: the
    SMPL / MANO file that AIST++ / HanCo are meshed with (`body_model_source`). `extra_meta`:
    entries meta.json records beside the reader's (a capture's up axis, frame rate, units).

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
    if set(form.split("+")) <= set(FORMS) and (source / "meta.json").is_file():
        # The prepared set's meta.json takes the source's, its tree in nmjax's convention.
        meta = read_meta_file(source / "meta.json")
    meta.update(extra_meta or {}, format=form)
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
        available={n for s in listed for n in (s.name, *s.aliases)},
    )
    return summary if note is None else dataclasses.replace(summary, notes=(note,))


def prepare_capture(
    source: Path,
    root: Path,
    *,
    up: str | None = None,
    fps: float | None = None,
    units: str | None = None,
    points: int = DEFAULT_POINTS,
    seed: int = 0,
    sequences: int | Sequence[str] | None = None,
    max_frames: int | None = None,
    overwrite: bool = False,
) -> Summary:
    """Prepares a user's own capture in `source` (folders of mesh or point frames, or (T, N, 3)
    arrays: `raw_sequences`) under `root` as the generic `capture` set, its up axis, frame rate
    and units recorded in meta.json (`nmjax.data.layout.capture_meta`: z, 30 fps, m unless
    given). One sequence is cut into a train and a test part (`streaming.hold_out_test`).

    Returns:
      the `Summary`.

    Raises:
      FileNotFoundError / ValueError naming the bad input (`prepare_real`, `capture_meta`).
    """
    extra = capture_meta(up, fps, units)
    return prepare_real(
        CAPTURE,
        source,
        root,
        points=points,
        seed=seed,
        sequences=sequences,
        max_frames=max_frames,
        overwrite=overwrite,
        extra_meta=extra,
    )
