"""D-FAUST (Bogo et al. 2017) registrations as downloaded: `registrations_{m,f}.hdf5`.

Each file holds one dataset per registered sequence, named `<subject>_<motion>` (`50002_hips`),
of shape (V, 3, T): the V registered vertices of every frame, xyz, T frames; and one dataset
`faces` (F, 3), the triangles they all share. Listing reads the shapes and the faces only; a
sequence's vertices are read on its turn (the two files are about 50 GB) and transposed to
(T, V, 3). The registrations carry no joints.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from nmjax.data.streaming import SourceSequence, sample_mesh_sequence

REGISTRATION_FILES = ("registrations_m.hdf5", "registrations_f.hdf5")
FACES_KEY = "faces"


def registration_files(source: Path) -> list[Path]:
    """The D-FAUST registration files present in `source`."""
    return [source / name for name in REGISTRATION_FILES if (source / name).is_file()]


def _open(path: Path):
    import h5py  # lazy: keeps `nmjax --help` fast

    try:
        return h5py.File(path, "r")
    except OSError as err:
        raise ValueError(f"{path}: not a readable HDF5 file ({err}); download it again") from err


def read_faces(path: Path, registrations) -> np.ndarray:
    """(F, 3) int64 triangles of the open registrations file `registrations` (at `path`).

    Raises:
      ValueError naming `path`: no `faces` dataset, or not (F, 3) non-negative whole numbers.
    """
    import h5py

    item = registrations.get(FACES_KEY)
    if not isinstance(item, h5py.Dataset):
        raise ValueError(
            f"{path}: no {FACES_KEY!r} dataset (the triangles shared by every registration); "
            f"is it {' or '.join(REGISTRATION_FILES)} as downloaded?"
        )
    faces = np.asarray(item[()])
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
        raise ValueError(f"{path}: {FACES_KEY!r} must have shape (F, 3), got {faces.shape}")
    if (
        not np.issubdtype(faces.dtype, np.number)
        or np.any(faces != np.round(faces))
        or (faces.min() < 0)
    ):
        raise ValueError(f"{path}: {FACES_KEY!r} must hold vertex indices (whole numbers >= 0)")
    return faces.astype(np.int64)


def read_registration(path: Path, key: str, num_frames: int) -> np.ndarray:
    """(num_frames, V, 3) float32: the first frames of registration `key` in `path`."""
    with _open(path) as registrations:
        block = registrations[key][:, :, :num_frames]
    return np.ascontiguousarray(np.asarray(block, dtype=np.float32).transpose(2, 0, 1))


def registration_sequences(
    source: Path, subjects: Sequence[str] | None = None
) -> list[SourceSequence]:
    """Lists the registrations in `source`'s `registrations_{m,f}.hdf5` (either or both).

    Args:
      source: the folder holding the downloaded files.
      subjects: subject ids to keep (`--subjects`); None for all.

    Returns:
      one `SourceSequence` per registration, named by its key; its motion (the key without the
      subject) is an alias, so `--sequences hips` picks hips of every subject.

    Raises:
      ValueError naming the file: unreadable, no `faces`, a key that is no `<subject>_<motion>`
      dataset of shape (V, 3, T) with V covering the faces, a key in both files, or a subject
      in `subjects` that none holds.
    """
    import h5py

    found: dict[str, SourceSequence] = {}
    for path in registration_files(source):
        with _open(path) as registrations:
            faces = read_faces(path, registrations)
            for key, item in registrations.items():
                if key == FACES_KEY:
                    continue
                subject, _, motion = key.partition("_")
                shape = getattr(item, "shape", None)
                if not isinstance(item, h5py.Dataset) or not subject or not motion:
                    raise ValueError(
                        f"{path}: {key!r} is not a registration (a dataset named "
                        "<subject>_<motion>, e.g. 50002_hips)"
                    )
                if len(shape) != 3 or shape[1] != 3 or shape[0] <= faces.max():
                    raise ValueError(
                        f"{path}: {key!r} has shape {shape}; a registration is (V, 3, T), "
                        f"V >= {faces.max() + 1} vertices (the faces use them), xyz, T frames"
                    )
                if key in found:
                    raise ValueError(f"{path}: {key!r} is in both registration files; keep one")

                def read(
                    points: int, seeds: np.ndarray, path: Path = path, key: str = key, faces=faces
                ) -> dict:
                    vertices = read_registration(path, key, len(seeds))
                    where = f"{path}:{key}"
                    return {"vertices": sample_mesh_sequence(vertices, faces, points, seeds, where)}

                found[key] = SourceSequence(key, int(shape[2]), read, aliases=(motion,))
    if subjects is not None:
        held = sorted({key.partition("_")[0] for key in found})
        missing = sorted(set(subjects) - set(held))
        if missing:
            files = ", ".join(str(p) for p in registration_files(source))
            raise ValueError(
                f"--subjects {','.join(missing)}: not in {files} (subjects there: "
                f"{', '.join(held)})"
            )
        found = {key: seq for key, seq in found.items() if key.partition("_")[0] in subjects}
    return list(found.values())
