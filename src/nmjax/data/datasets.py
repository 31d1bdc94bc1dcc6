"""Dataset registry and loaders: point-cloud sequences with optional ground-truth joints.

Prepared layout (written by `nmjax prepare-data` or by `nmjax.data.synthetic.generate`):

    <root>/<split>/vertices/<seq>.npy   (T, N, 3) float32 points of one sequence
    <root>/<split>/joints/<seq>.npy     (T, J, 3) ground-truth joints (optional;
                                        HanCo names them <seq>_joints.npy)
    <root>/meta.json                    optional: joint_names, parents, sample_rate, ...
    <root>/split.json                   optional: {"train": [seq, ...], "test": [seq, ...]}

`<root>` defaults to `data/<name>` relative to the working directory, or `$NMJAX_DATA/<name>`
when the environment variable is set. When `split.json` is present its lists decide the split;
otherwise the `<split>/` folders do, and a dataset whose sequences all sit in `<root>/vertices/`
(no split folders) is divided 9:1 by frame count with `split_by_frames`. Synthetic datasets
(`synth-*`) are generated on first use.

`crop_sequence` and `sample_start` implement the sequence crop of paper Sec. B.1: a random start
frame, T frames at the dataset's sample rate, sequences that are too short padded by repeating
their last frame.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path

import numpy as np

from nmjax.config import DATASETS, dataset_spec

REAL_DATASETS = ("hanco", "aist", "dfaust", "animals", "panda")
SYNTHETIC_DATASETS = tuple(name for name, spec in DATASETS.items() if spec.synthetic)
SPLITS = ("train", "test")
TEST_FRACTION = 0.1  # the 9:1 split

# How each dataset names its ground-truth joint files inside <split>/joints/.
JOINT_FILE_PATTERNS: dict[str, str] = {name: "{seq}.npy" for name in DATASETS}
JOINT_FILE_PATTERNS["hanco"] = "{seq}_joints.npy"

_CHECK_CHUNK = 64  # frames per chunk when scanning a (memory-mapped) file for NaN / inf


@dataclasses.dataclass(frozen=True)
class Sequence:
    """One point-cloud sequence.

    Attributes:
      name: sequence id (the file stem).
      vertices: (T, N, 3) float32 points; a read-only memory map when the file is float32.
      joints: (T, J, 3) float32 ground-truth joints, or None.
      path: the vertices file.
      joints_path: the joints file, or None.
    """

    name: str
    vertices: np.ndarray
    joints: np.ndarray | None
    path: Path
    joints_path: Path | None = None

    @property
    def num_frames(self) -> int:
        return int(self.vertices.shape[0])


def dataset_root(name: str, root: str | os.PathLike | None = None) -> Path:
    """Folder of dataset `name`: `root` if given, else `$NMJAX_DATA/<name>`, else `data/<name>`."""
    dataset_spec(name)  # unknown names list the valid ones
    if root is not None:
        return Path(root)
    base = os.environ.get("NMJAX_DATA")
    return Path(base) / name if base else Path("data") / name


def _missing_message(name: str, folder: Path, what: str) -> str:
    if name in SYNTHETIC_DATASETS:
        how = f"nmjax prepare-data --data {name} --root {folder}"
    else:
        how = (
            f"nmjax prepare-data --data {name} --from DIR --root {folder}\n"
            "    (DIR: the raw mesh sequences, one folder of .obj/.ply/.off frames per sequence)"
        )
    return (
        f"dataset {name!r}: {what} {folder} not found.\n"
        f"  Prepare it with: {how}\n"
        "  or point --root / NMJAX_DATA at a prepared copy,\n"
        "  or train on a built-in synthetic dataset instead: DATA=synth-hand"
    )


def _open_array(path: Path) -> np.ndarray:
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:
        raise ValueError(
            f"{path}: not a readable .npy array ({err}); regenerate it with nmjax prepare-data"
        ) from err


def _check_finite(path: Path, array: np.ndarray, what: str) -> None:
    # Checked in float32, the dtype the loaders return: a float64 value beyond its range would
    # pass a float64 check and become inf.
    for start in range(0, array.shape[0], _CHECK_CHUNK):
        with np.errstate(over="ignore", invalid="ignore"):
            chunk = np.asarray(array[start : start + _CHECK_CHUNK], np.float32)
        if not np.isfinite(chunk).all():
            bad = start + int(np.argwhere(~np.isfinite(chunk))[0, 0])
            raise ValueError(
                f"{path}: {what} contain NaN, inf or values beyond the float32 range (first at "
                f"frame {bad})"
            )


def read_vertices(path: str | os.PathLike) -> np.ndarray:
    """Loads and validates one (T, N, 3) point file; float32 files stay memory-mapped.

    Raises:
      ValueError naming `path` for an unreadable file, a wrong shape, no points per frame, fewer
      than 2 frames, or NaN / inf values.
    """
    path = Path(path)
    array = _open_array(path)
    if array.ndim != 3 or array.shape[-1] != 3:
        raise ValueError(f"{path}: vertices must have shape (T, N, 3), got {array.shape}")
    if not np.issubdtype(array.dtype, np.floating):
        raise ValueError(f"{path}: vertices must be floating point, got dtype {array.dtype}")
    if array.shape[1] == 0:
        raise ValueError(f"{path}: empty frames (0 points per frame, shape {array.shape})")
    if array.shape[0] < 2:
        raise ValueError(f"{path}: a sequence needs at least 2 frames, got {array.shape[0]}")
    _check_finite(path, array, "vertices")
    return array if array.dtype == np.float32 else np.asarray(array, dtype=np.float32)


def read_joints(path: str | os.PathLike, num_frames: int) -> np.ndarray:
    """Loads and validates one (T, J, 3) joint file whose T must equal `num_frames`."""
    path = Path(path)
    array = _open_array(path)
    if array.ndim != 3 or array.shape[-1] != 3 or array.shape[1] == 0:
        raise ValueError(f"{path}: joints must have shape (T, J, 3) with J > 0, got {array.shape}")
    if not np.issubdtype(array.dtype, np.floating):
        raise ValueError(f"{path}: joints must be floating point, got dtype {array.dtype}")
    if array.shape[0] != num_frames:
        raise ValueError(
            f"{path}: {array.shape[0]} joint frames but the vertices file has {num_frames}; "
            "both must cover the same frames"
        )
    _check_finite(path, array, "joints")
    return array if array.dtype == np.float32 else np.asarray(array, dtype=np.float32)


def split_by_frames(frame_counts: dict[str, int]) -> dict[str, list[str]]:
    """Deterministic 9:1 train/test split of whole sequences, measured in frames.

    Sequences are ordered by a hash of their name (stable across runs and machines, independent
    of file-system order) and moved to the test split until it holds >= 10% of all frames; at
    least one sequence stays in train. A single sequence goes to train only.

    Args:
      frame_counts: sequence name -> number of frames.

    Returns:
      {"train": sorted names, "test": sorted names}.
    """
    names = sorted(frame_counts, key=lambda s: hashlib.sha256(s.encode()).hexdigest())
    total = sum(frame_counts.values())
    test: list[str] = []
    held = 0
    for name in names[:-1]:
        if held >= TEST_FRACTION * total:
            break
        test.append(name)
        held += frame_counts[name]
    held_out = set(test)
    train = [name for name in names if name not in held_out]
    return {"train": sorted(train), "test": sorted(test)}


def read_split_file(path: Path) -> dict[str, list[str]]:
    """Reads `split.json` {"train": [...], "test": [...]} with clear errors."""
    try:
        split = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: unreadable split file ({err})") from err
    if not isinstance(split, dict) or not all(
        isinstance(split.get(s), list) and all(isinstance(n, str) for n in split[s]) for s in SPLITS
    ):
        raise ValueError(f'{path}: expected {{"train": [names...], "test": [names...]}}')
    return {s: list(split[s]) for s in SPLITS}


def _sequence_files(root: Path) -> dict[str, tuple[Path, Path]]:
    """seq name -> (vertices file, joints folder) over <root>/vertices and <root>/<split>/."""
    found: dict[str, tuple[Path, Path]] = {}
    for folder in [root, *(root / s for s in SPLITS)]:
        for path in sorted((folder / "vertices").glob("*.npy")):
            if path.stem in found:
                raise ValueError(
                    f"sequence {path.stem!r} appears twice: {found[path.stem][0]} and {path}"
                )
            found[path.stem] = (path, folder / "joints")
    return found


def _ensure_generated(name: str, root: Path) -> None:
    folders = [root / "vertices", *(root / s / "vertices" for s in SPLITS)]
    if (root / "meta.json").is_file() and any(f.is_dir() for f in folders):
        return
    from nmjax.data import synthetic  # lazy: generation needs trimesh

    synthetic.generate(name, root)


def load_sequences(
    name: str, split: str = "train", root: str | os.PathLike | None = None
) -> list[Sequence]:
    """Loads the `split` sequences of dataset `name`, sorted by sequence name.

    Args:
      name: a registered dataset (`nmjax.config.DATASETS`).
      split: "train" or "test".
      root: dataset folder; default `dataset_root(name)`.

    Returns:
      list of validated `Sequence`s.

    Raises:
      FileNotFoundError: the dataset folder (or its sequences) does not exist; the message says
        how to prepare it.
      ValueError: a bad file (named in the message), an unknown name or split, an empty split.
    """
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    folder = dataset_root(name, root)
    if name in SYNTHETIC_DATASETS:
        _ensure_generated(name, folder)
    if not folder.is_dir():
        raise FileNotFoundError(_missing_message(name, folder, "dataset folder"))
    files = _sequence_files(folder)
    if not files:
        raise FileNotFoundError(
            _missing_message(name, folder / "<split>" / "vertices", "sequence folder")
        )
    split_file = folder / "split.json"
    if split_file.is_file():
        chosen = read_split_file(split_file)[split]
        missing = [seq for seq in chosen if seq not in files]
        if missing:
            raise ValueError(
                f"{split_file}: {split} lists sequences with no vertices file: {missing[:5]}"
            )
    elif (folder / split / "vertices").is_dir() or not (folder / "vertices").is_dir():
        chosen = sorted(p.stem for p in (folder / split / "vertices").glob("*.npy"))
    else:  # one unsplit pool: 9:1 by frame count
        counts = {seq: int(_open_array(path).shape[0]) for seq, (path, _) in files.items()}
        chosen = split_by_frames(counts)[split]
    if not chosen:
        raise ValueError(
            f"dataset {name!r} at {folder} has no {split!r} sequences; add some to "
            f"{folder / split / 'vertices'} or list them in {split_file}"
        )
    pattern = JOINT_FILE_PATTERNS[name]
    sequences = []
    for seq in sorted(chosen):
        vertices_path, joints_folder = files[seq]
        vertices = read_vertices(vertices_path)
        joints, joints_path = None, None
        for candidate in dict.fromkeys([pattern.format(seq=seq), f"{seq}.npy"]):
            if (joints_folder / candidate).is_file():
                joints_path = joints_folder / candidate
                joints = read_joints(joints_path, vertices.shape[0])
                break
        sequences.append(Sequence(seq, vertices, joints, vertices_path, joints_path))
    return sequences


def read_meta(name: str, root: str | os.PathLike | None = None) -> dict:
    """`<root>/meta.json` of a dataset as a dict ({} when the dataset has none)."""
    path = dataset_root(name, root) / "meta.json"
    if not path.is_file():
        return {}
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: invalid JSON ({err})") from err


def crop_span(frames: int, sample_rate: int) -> int:
    """Original frames covered by a crop of `frames` frames taken every `sample_rate` frames."""
    return (frames - 1) * sample_rate + 1


def sample_start(rng: np.random.Generator, num_frames: int, frames: int, sample_rate: int) -> int:
    """Random first frame of a crop (Sec. B.1), uniform over the starts that fit; 0 if none does."""
    return int(rng.integers(0, max(num_frames - crop_span(frames, sample_rate), 0) + 1))


def crop_indices(num_frames: int, frames: int, sample_rate: int, start: int) -> np.ndarray:
    """(frames,) frame indices start, start + rate, ...; past the end they repeat the last frame."""
    if frames < 1 or sample_rate < 1:
        raise ValueError(f"frames and sample_rate must be >= 1, got {frames}, {sample_rate}")
    if not 0 <= start < num_frames:
        raise ValueError(f"crop start {start} outside the sequence's {num_frames} frames")
    return np.minimum(start + sample_rate * np.arange(frames), num_frames - 1)


def crop_sequence(
    seq: Sequence, frames: int, sample_rate: int, start: int
) -> tuple[np.ndarray, np.ndarray | None]:
    """`frames` frames of `seq` from `start` every `sample_rate` frames, padded with the last.

    Returns:
      (vertices (frames, N, 3) float32, joints (frames, J, 3) float32 or None), in memory.
    """
    idx = crop_indices(seq.num_frames, frames, sample_rate, start)
    vertices = np.asarray(seq.vertices[idx], dtype=np.float32)
    joints = None if seq.joints is None else np.asarray(seq.joints[idx], dtype=np.float32)
    return vertices, joints
