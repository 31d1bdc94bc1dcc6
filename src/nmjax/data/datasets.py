"""Dataset loaders: the point-cloud sequences of a split, validated, with optional joints.

The files are laid out as `nmjax.data.layout` describes (written by `nmjax prepare-data` or by
`nmjax.data.synthetic.generate`). When `split.json` is present its lists decide the split;
otherwise the `<split>/` folders do, and a dataset whose sequences all sit in `<root>/vertices/`
(no split folders) is divided 9:1 by frame count with `layout.split_by_frames`. Loading never
writes: a synthetic set (`synth-*`) that is missing or unfinished is an error naming the command
that generates it; `nmjax.data.synthetic.ensure_dataset` is the explicit step that does.

`crop_sequence` and `sample_start` implement the sequence crop of paper Sec. B.1: a random start
frame, T frames at the dataset's sample rate, sequences that are too short padded by repeating
their last frame.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from nmjax.data import layout

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


def _missing_message(name: str, root: Path, missing: Path, what: str) -> str:
    if name in layout.SYNTHETIC_DATASETS:
        how = f"nmjax prepare-data --data {name} --root {root}"
        instead = "  or call nmjax.data.synthetic.ensure_dataset first"
    else:
        how = (
            f"nmjax prepare-data --data {name} --from DIR --root {root}\n"
            "    (DIR: the download as it comes, see nmjax prepare-data --help, or one folder of\n"
            "    .obj/.ply/.off frames per sequence)"
        )
        instead = "  or train on a built-in synthetic dataset instead: DATA=synth-hand"
    return (
        f"dataset {name!r}: {what} {missing} not found.\n"
        f"  Prepare it with: {how}\n"
        f"  or point --root / NMJAX_DATA at a prepared copy,\n{instead}"
    )


def _check_generated(name: str, root: Path) -> None:
    """A synthetic set is only read once its generator has finished (meta.json marks it)."""
    if not root.is_dir():
        raise FileNotFoundError(_missing_message(name, root, root, "generated set"))
    if not layout.is_complete(root):
        raise FileNotFoundError(
            f"dataset {name!r}: {root} holds no finished generated set (meta.json does not say "
            '"complete": true; an interrupted generation?).\n'
            f"  Generate it again with: nmjax prepare-data --data {name} --root {root} --overwrite"
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


def load_sequences(
    name: str, split: str = "train", root: str | os.PathLike | None = None
) -> list[Sequence]:
    """Loads the `split` sequences of dataset `name`, sorted by sequence name.

    Args:
      name: a registered dataset (`nmjax.config.DATASETS`).
      split: "train" or "test".
      root: dataset folder; default `layout.dataset_root(name)`.

    Returns:
      list of validated `Sequence`s.

    Raises:
      FileNotFoundError: the dataset folder (or its sequences) does not exist, or a synthetic set
        is not generated yet or unfinished; the message names the command that prepares it.
      ValueError: a bad file (named in the message), an unknown name or split, an empty split.
    """
    if split not in layout.SPLITS:
        raise ValueError(f"split must be one of {layout.SPLITS}, got {split!r}")
    folder = layout.dataset_root(name, root)
    if name in layout.SYNTHETIC_DATASETS:
        _check_generated(name, folder)
    if not folder.is_dir():
        raise FileNotFoundError(_missing_message(name, folder, folder, "dataset folder"))
    if (folder / layout.PREPARING_FILE).is_file() and not (folder / "meta.json").is_file():
        raise FileNotFoundError(
            f"dataset {name!r}: {folder} holds an unfinished preparation "
            f"({layout.PREPARING_FILE}, no meta.json).\n"
            "  Finish it by running the same nmjax prepare-data command again"
        )
    files = layout.sequence_files(folder)
    if not files:
        raise FileNotFoundError(
            _missing_message(name, folder, folder / "<split>" / "vertices", "sequence folder")
        )
    split_file = folder / "split.json"
    if split_file.is_file():
        chosen = layout.read_split_file(split_file)[split]
        missing = [seq for seq in chosen if seq not in files]
        if missing:
            raise ValueError(
                f"{split_file}: {split} lists sequences with no vertices file: {missing[:5]}"
            )
    elif (folder / split / "vertices").is_dir() or not (folder / "vertices").is_dir():
        chosen = sorted(p.stem for p in (folder / split / "vertices").glob("*.npy"))
    else:  # one unsplit pool: 9:1 by frame count
        counts = {seq: int(_open_array(path).shape[0]) for seq, (path, _) in files.items()}
        chosen = layout.split_by_frames(counts)[split]
    if not chosen:
        raise ValueError(
            f"dataset {name!r} at {folder} has no {split!r} sequences; add some to "
            f"{folder / split / 'vertices'} or list them in {split_file}"
        )
    sequences = []
    for seq in sorted(chosen):
        vertices_path, joints_folder = files[seq]
        vertices = read_vertices(vertices_path)
        joints_path = layout.joints_file(name, joints_folder, seq)
        joints = None if joints_path is None else read_joints(joints_path, vertices.shape[0])
        sequences.append(Sequence(seq, vertices, joints, vertices_path, joints_path))
    return sequences


def whole_sequence(name: str, seq: str, root: str | os.PathLike | None = None) -> np.ndarray:
    """(T, N, 3) float32: every frame of the raw sequence `seq` of a prepared set, in order.

    A sequence `prepare-data` cut into a training and a test part (a single sequence; meta.json's
    `cut_from`, `nmjax.data.streaming.hold_out_test`) is put back together from its parts; any
    other is the sequence as written, from whichever split holds it.

    Raises:
      ValueError: `seq` is neither a prepared sequence nor one that was cut (naming those there),
        or its parts leave frames out.
    """
    loaded = {s.name: s for split in layout.SPLITS for s in load_sequences(name, split, root)}
    cut = layout.read_meta(name, root).get("cut_from") or {}
    parts = {part: info["frames"] for part, info in cut.items() if info.get("sequence") == seq}
    if not parts:
        if seq not in loaded:
            held = sorted({*loaded, *(i.get("sequence") for i in cut.values())} - set(cut))
            raise ValueError(
                f"{layout.dataset_root(name, root)} holds no sequence {seq!r}; it holds "
                f"{', '.join(map(str, held[:8]))}"
            )
        return np.asarray(loaded[seq].vertices, np.float32)
    end = max(hi for _, hi in parts.values())
    first = loaded[next(iter(parts))].vertices
    out = np.empty((end, *first.shape[1:]), np.float32)
    covered = np.zeros(end, bool)
    for part, (lo, hi) in parts.items():
        out[lo:hi] = loaded[part].vertices
        covered[lo:hi] = True
    if not covered.all():
        raise ValueError(
            f"{layout.dataset_root(name, root)}: the parts of {seq!r} in meta.json's cut_from "
            f"leave frames out ({cut}); prepare the capture again"
        )
    return out


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


def pad_with_last(x: np.ndarray, length: int) -> np.ndarray:
    """`x` (N, ...) extended to at least `length` along axis 0 by repeating its last entry (a
    sequence's last frame, a batch's last crop); unchanged when it is long enough."""
    if len(x) >= length:
        return x
    return np.concatenate([x, np.repeat(x[-1:], length - len(x), axis=0)])
