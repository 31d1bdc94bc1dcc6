"""A real dataset written one sequence at a time: the part every `prepare-data` reader shares.

A reader (mesh folders in `nmjax.data.prepare`, `nmjax.data.dt4d`, `nmjax.data.dfaust`, ...)
first lists its sequences as `SourceSequence`s, names and frame counts from headers only, so that
a bad input is refused before anything is written. `write_sequences` then picks the split
(`choose_split`), asks each sequence for its arrays in turn and writes them atomically, joints
first and vertices last, so that a vertices file marks a finished sequence. A rerun skips every
sequence whose vertices file already holds the expected shape (moving it across when the split
changed), so that an interrupted preparation of a large download continues where it stopped;
`<root>/preparing.json` records the settings of an unfinished preparation, and a rerun with other
settings is refused (`--overwrite` starts again). `split.json` and `meta.json` come last.

A single sequence split 9:1 by frames would leave no test split, so it is cut in two instead
(`hold_out_test`): its last 10% of frames, at least one training crop long, become the test
sequence `<seq>_test`; one too short for that is scored on a copy of itself, `<seq>_test`, and
the summary says which.

Surface points: `nmjax.data.meshes.sample_surface` samples one mesh frame area-uniformly
(trimesh), `nmjax.data.prepare.resample_points` resamples a point-cloud frame, each with a seed
from `sequence_seeds`, which depends on the sequence's name and frame only, so that
preparing a part of a set (`--sequences`, `--frames`, `--subjects`) gives the same bytes as
preparing all of it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import time
from collections.abc import Callable, Collection, Sequence
from pathlib import Path

import numpy as np

from nmjax import atomic
from nmjax.config import DATASETS, PRESETS, skel_preset
from nmjax.data import layout, splits
from nmjax.data.meshes import sample_surface

ReadArrays = Callable[[int, np.ndarray], dict[str, np.ndarray | None]]


@dataclasses.dataclass(frozen=True)
class SourceSequence:
    """One raw sequence as a reader lists it, before its frames are read.

    Attributes:
      name: the sequence's name in the prepared set.
      num_frames: frames the raw sequence holds.
      read: `read(points, seeds)` reads and samples the first `len(seeds)` frames, frame t with
        seed `seeds[t]`, and returns the arrays to write by kind: "vertices" (T, points, 3)
        float32 and, where the source has them, "joints" (T, J, 3). Called once, on its turn.
      aliases: further names `--sequences` picks it by (D-FAUST: the motion without the subject).
    """

    name: str
    num_frames: int
    read: ReadArrays
    aliases: tuple[str, ...] = ()


@dataclasses.dataclass(frozen=True)
class Summary:
    """What `write_sequences` did; `line()` is the summary `nmjax prepare-data` prints."""

    name: str
    root: Path
    split: dict[str, list[str]]
    rule: str  # where the split came from
    written: int
    skipped: int
    frames: int
    points: int
    seconds: float
    left_out: list[str]
    notes: tuple[str, ...] = ()  # what the reader adds (AIST++: the ignore list, ...)
    source: Path | None = None  # the --from folder

    def line(self) -> str:
        done = self.written + self.skipped
        text = (
            f"prepared {self.name} in {self.root}: {done} sequences ({self.written} written, "
            f"{self.skipped} already there), {self.frames:,} frames, {self.points:,} points, "
            f"train {len(self.split['train'])} / test {len(self.split['test'])} ({self.rule}), "
            f"{self.seconds:.1f} s"
        )
        if self.left_out:
            shown = ", ".join(self.left_out[:5]) + (", ..." if len(self.left_out) > 5 else "")
            text += f"; {len(self.left_out)} in neither published list, left out: {shown}"
        if not self.split["test"]:
            where = "split.json" if self.source is None else self.source / "split.json"
            text += (
                "; no test sequence, and nmjax train-skel stops without one (it validates and "
                f'scores on it): list one under "test" in {where}'
            )
        return "; ".join([text, *self.notes])


# --- sampling ------------------------------------------------------------------------------------


def sequence_seeds(seed: int, name: str, num_frames: int) -> np.ndarray:
    """(num_frames,) uint32 sampling seeds of sequence `name`, one per frame.

    They depend on `seed`, the name and the frame index only: the first T seeds of a longer
    sequence are the seeds of its first T frames.
    """
    key = int.from_bytes(hashlib.sha256(name.encode()).digest()[:8], "little")
    return np.random.SeedSequence([seed, key]).generate_state(num_frames)


def sample_mesh_sequence(
    vertices: np.ndarray, faces: np.ndarray, points: int, seeds: np.ndarray, where: str
) -> np.ndarray:
    """(T, points, 3) float32 surface points of a mesh sequence with one topology.

    Args:
      vertices: (T, V, 3) vertex positions per frame.
      faces: (F, 3) vertex indices of the triangles, the same in every frame.
      points: points per frame.
      seeds: (T,) one sampling seed per frame (`sequence_seeds`).
      where: the source, for error messages.

    Raises:
      ValueError naming `where`: face indices outside the vertices, NaN / inf vertices, a frame
      without surface.
    """
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"{where}: faces must be (F, 3) integer indices, got {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= vertices.shape[1]):
        raise ValueError(
            f"{where}: face indices {faces.min()}..{faces.max()} outside the "
            f"{vertices.shape[1]} vertices"
        )
    bad = ~np.isfinite(vertices[: len(seeds)]).all(axis=(1, 2))
    if bad.any():
        raise ValueError(f"{where}: vertices contain NaN or inf (first at frame {np.argmax(bad)})")
    sampled = np.empty((len(seeds), points, 3), dtype=np.float32)
    for t, frame_seed in enumerate(seeds):
        where_t = f"{where} frame {t}"
        sampled[t] = sample_surface(vertices[t], faces, points, int(frame_seed), where_t)
    return sampled


# --- which sequences, which split ---------------------------------------------------------------


def select_sequences(
    sequences: Sequence[SourceSequence], chosen: int | Sequence[str] | None, source: Path
) -> list[SourceSequence]:
    """The `--sequences` part of `sequences` (sorted by name): all (None), the first N, or those
    named (by name or alias).

    Raises:
      ValueError: a name that matches no sequence.
    """
    ordered = sorted(sequences, key=lambda s: s.name)
    if chosen is None:
        return ordered
    if isinstance(chosen, int):
        return ordered[:chosen]
    wanted = set(chosen)
    picked = [s for s in ordered if wanted & {s.name, *s.aliases}]
    unknown = sorted(wanted - {n for s in picked for n in (s.name, *s.aliases)})
    if unknown:
        raise ValueError(
            f"--sequences: {', '.join(unknown[:5])} not in {source} (it holds "
            f"{', '.join(s.name for s in ordered[:5])}{', ...' if len(ordered) > 5 else ''})"
        )
    return picked


SPLIT_BY_FRAMES = "9:1 by frames"  # the rule `choose_split` names when nothing else applies


def choose_split(
    name: str,
    frame_counts: dict[str, int],
    source: Path,
    *,
    published: bool,
    available: Collection[str] | None = None,
) -> tuple[dict[str, list[str]], list[str], str]:
    """The train/test split of the sequences `frame_counts` (name -> frames).

    In order: `source/split.json` when present (every sequence must be in it, and it may name
    only sequences `source` holds: `available`, default those of `frame_counts`); the published
    lists of `name` (`nmjax.data.splits`) when `published` and the set has them; else 9:1 by
    frames (`SPLIT_BY_FRAMES`).

    Returns:
      (split, names left out: in neither published list, the rule that was used).

    Raises:
      ValueError: a sequence missing from split.json, a name in it that `source` lacks, or every
        sequence in neither published list.
    """
    split_file = source / "split.json"
    if split_file.is_file():
        split = layout.read_split_file(split_file)
        held = set(frame_counts if available is None else available)
        unknown = sorted({seq for s in layout.SPLITS for seq in split[s]} - held)
        if unknown:
            shown = ", ".join(sorted(held)[:5]) + (", ..." if len(held) > 5 else "")
            raise ValueError(
                f"{split_file} names {', '.join(unknown[:5])}, which {source} does not hold (it "
                f"holds {shown}); correct or remove the name"
            )
        split = {s: sorted(seq for seq in split[s] if seq in frame_counts) for s in layout.SPLITS}
        unlisted = sorted(set(frame_counts) - set(split["train"]) - set(split["test"]))
        if unlisted:
            raise ValueError(f"{split_file}: sequences in neither split: {unlisted[:5]}")
        return split, [], str(split_file)
    if published and name in splits.PUBLISHED_SPLITS:
        split, left_out = splits.published_split(name, frame_counts)
        if left_out and len(left_out) == len(frame_counts):
            unit = splits.PUBLISHED_SPLITS[name]
            raise ValueError(
                f"--from {source}: none of its {len(left_out)} sequences ({left_out[0]}, ...) "
                f"is in the published {name} split (listed by {unit}); is it the {name} download?"
            )
        return split, left_out, f"published {name} split"
    return layout.split_by_frames(frame_counts), [], SPLIT_BY_FRAMES


def held_out_frames(name: str, num_frames: int) -> int:
    """Frames `hold_out_test` holds out of a single sequence of `num_frames` frames of dataset
    `name`: the last 10% (`layout.TEST_FRACTION`), at least the longest training crop of any
    preset (its frames at the dataset's sample rate; 10 frames at rate 1)."""
    crop = max(skel_preset(name, preset).data.frames for preset in PRESETS)
    span = (crop - 1) * DATASETS[name].sample_rate + 1
    return max(math.ceil(layout.TEST_FRACTION * num_frames), span)


def hold_out_test(
    name: str, seq: SourceSequence, num_frames: int, seed: int
) -> tuple[list[SourceSequence], dict[str, dict], str]:
    """A single sequence as a train and a test sequence (9:1 by frames would leave no test).

    The last `held_out_frames` frames become `<seq>_test`, the rest `<seq>`, when that rest is at
    least as long as the test part (a training crop); a shorter sequence stays whole and
    `<seq>_test` is a copy of it, scored on the frames it trains on. Both parts are sliced from
    one read of the sequence with its own seeds, so they hold the points a preparation of the
    whole sequence would.

    Returns:
      (the two parts, train part first; meta.json's `cut_from`, {part: {"sequence": the name,
      "frames": [first, end)}}; the rule, for the summary and meta.json).
    """
    held = held_out_frames(name, num_frames)
    test_name = f"{seq.name}_test"
    if num_frames - held >= held:
        cut = num_frames - held
        ranges = {seq.name: [0, cut], test_name: [cut, num_frames]}
        rule = (
            f"one sequence: its last {held} of {num_frames} frames (10%, at least a training "
            f"crop) are the test sequence {test_name}"
        )
    else:
        ranges = {seq.name: [0, num_frames], test_name: [0, num_frames]}
        rule = (
            f"one sequence of {num_frames} frames, too short to hold out {held} (that needs "
            f"{2 * held}): {test_name} is a copy of it, so its test scores are on training frames"
        )
    whole: dict[str, np.ndarray | None] = {}

    def part(lo: int, hi: int, last: bool) -> ReadArrays:
        def read(points: int, seeds: np.ndarray) -> dict[str, np.ndarray | None]:
            if not whole:  # the part's own seeds give way to the whole sequence's
                whole.update(seq.read(points, sequence_seeds(seed, seq.name, num_frames)))
            arrays = {k: None if v is None else v[lo:hi] for k, v in whole.items()}
            if last:
                whole.clear()
            return arrays

        return read

    parts = [
        SourceSequence(part_name, hi - lo, part(lo, hi, part_name == test_name))
        for part_name, (lo, hi) in ranges.items()
    ]
    return parts, {k: {"sequence": seq.name, "frames": v} for k, v in ranges.items()}, rule


# --- writing -------------------------------------------------------------------------------------


def _check_settings(root: Path, settings: dict) -> None:
    """Records the settings of a new preparation; refuses to continue one made with others."""
    path = root / layout.PREPARING_FILE
    if path.is_file():
        try:
            before = json.loads(path.read_text())
        except json.JSONDecodeError:
            before = None
        if not isinstance(before, dict) or any(
            before.get(k) != settings[k] for k in ("name", "points", "seed")
        ):
            raise ValueError(
                f"{root} holds an unfinished preparation made with other settings ({path}: "
                f"{before}); rerun with those, or pass --overwrite to start again"
            )
    atomic.write_json(path, settings)


def _finished(root: Path, seq: str, split: str, shape: tuple[int, ...], joint_file: str) -> bool:
    """True when sequence `seq` is already written with `shape`: skipped, after moving its files
    into `split` if a previous run put it elsewhere. Other copies (a wrong shape) are removed."""
    done = False
    for where in (split, *(s for s in layout.SPLITS if s != split)):
        vertices = root / where / "vertices" / f"{seq}.npy"
        if not vertices.is_file():
            continue
        try:
            existing = np.load(vertices, mmap_mode="r", allow_pickle=False)
            good = existing.shape == shape and existing.dtype == np.float32
            del existing
        except (ValueError, OSError, EOFError):
            good = False
        joints = root / where / "joints" / joint_file.format(seq=seq)
        if good and not done:
            if where != split:  # joints first: a vertices file marks a finished sequence
                if joints.is_file():
                    (root / split / "joints").mkdir(parents=True, exist_ok=True)
                    os.replace(joints, root / split / "joints" / joints.name)
                (root / split / "vertices").mkdir(parents=True, exist_ok=True)
                os.replace(vertices, root / split / "vertices" / vertices.name)
            done = True
        elif where != split:  # a stale copy would make the sequence appear twice
            vertices.unlink()
            joints.unlink(missing_ok=True)
    return done


def _write_one(
    root: Path,
    split: str,
    seq: str,
    arrays: dict[str, np.ndarray | None],
    shape: tuple[int, ...],
    joint_file: str,
) -> None:
    arrays = dict(arrays)
    vertices = arrays.pop("vertices")
    if vertices.shape != shape:
        raise ValueError(f"sequence {seq}: vertices of shape {vertices.shape}, expected {shape}")
    # Vertices last: their file marks a finished sequence.
    vertices = vertices.astype(np.float32, copy=False)
    layout.write_sequence(root, split, seq, joint_file=joint_file, **arrays, vertices=vertices)


def _remove_empty_folders(root: Path) -> None:
    for folder in sorted((p for p in root.rglob("*") if p.is_dir()), reverse=True):
        if not any(folder.iterdir()):
            folder.rmdir()
    if root.is_dir() and not any(root.iterdir()):
        root.rmdir()


def write_sequences(
    name: str,
    root: Path,
    sequences: Sequence[SourceSequence],
    *,
    source: Path,
    points: int,
    seed: int = 0,
    max_frames: int | None = None,
    published: bool = False,
    meta: dict | None = None,
    overwrite: bool = False,
    available: Collection[str] | None = None,
) -> Summary:
    """Writes `sequences` (already selected) of dataset `name` into the layout under `root`.

    Args:
      name: a registered real dataset.
      root: the dataset folder.
      sequences: the listed raw sequences (`select_sequences` applied).
      source: the `--from` folder (its split.json, messages, meta.json).
      points: points per frame.
      seed: sampling seed (`sequence_seeds`).
      max_frames: `--frames`, the first frames of every sequence; None for all.
      published: split by the published lists of `name` (`choose_split`); for the downloads
        those lists are written for, not for hand-made mesh folders.
      meta: further entries for meta.json (the source format, the source's own meta.json).
      overwrite: clear what `root` holds (`layout.clear_dataset`) once the split is chosen,
        instead of skipping the sequences already written.
      available: every sequence name `source` holds, before the selection: a split.json may
        name these only (default: the names of `sequences`).

    A single sequence split by frames is cut in two (`hold_out_test`); meta.json's `cut_from`
    records the frames of each part.

    Returns:
      the `Summary`.

    Raises:
      ValueError: a sequence with fewer than 2 frames, an unfinished preparation made with other
        settings, a bad split.json, or whatever the readers refuse.
    """
    from tqdm import tqdm

    begin = time.perf_counter()
    frames = {s.name: min(s.num_frames, max_frames or s.num_frames) for s in sequences}
    short = [seq for seq, count in frames.items() if count < 2]
    if short:
        raise ValueError(f"--from {source}: sequences with fewer than 2 frames: {short[:5]}")
    split, left_out, rule = choose_split(
        name, frames, source, published=published, available=available
    )
    cut_from = None
    if len(sequences) == 1 and rule == SPLIT_BY_FRAMES:
        (whole,) = sequences
        sequences, cut_from, rule = hold_out_test(name, whole, frames[whole.name], seed)
        frames = {s.name: s.num_frames for s in sequences}
        split = {"train": [sequences[0].name], "test": [sequences[1].name]}
    if overwrite:
        layout.clear_dataset(root)
    settings = {"name": name, "points": points, "seed": seed, "source": str(source)}
    new_root = not root.exists()
    _check_settings(root, settings)
    joint_file = layout.JOINT_FILE_PATTERNS[name]
    by_name = {s.name: s for s in sequences}
    written = skipped = 0
    total = sum(len(split[s]) for s in layout.SPLITS)
    try:
        # disable=None: no bar when stderr is not a terminal (logs, tests): errors stay one line
        with tqdm(total=total, unit="seq", desc=f"prepare {name}", disable=None) as bar:
            for split_name in layout.SPLITS:
                for seq in split[split_name]:
                    bar.set_postfix_str(seq)
                    count = frames[seq]
                    if _finished(root, seq, split_name, (count, points, 3), joint_file):
                        skipped += 1
                    else:
                        arrays = by_name[seq].read(points, sequence_seeds(seed, seq, count))
                        _write_one(root, split_name, seq, arrays, (count, points, 3), joint_file)
                        written += 1
                    bar.update(1)
    except BaseException:
        if written == skipped == 0:  # nothing to continue from: leave no trace
            (root / layout.PREPARING_FILE).unlink(missing_ok=True)
            if new_root:
                _remove_empty_folders(root)
        raise
    kept = {seq: frames[seq] for s in layout.SPLITS for seq in split[s]}
    info = dict(meta or {})
    info.update(
        name=name,
        sample_rate=DATASETS[name].sample_rate,
        points=points,
        seed=seed,
        source=str(source),
        split_rule=rule,
        left_out=left_out,
        frames=kept,
    )
    if cut_from is not None:
        info["cut_from"] = cut_from
    layout.write_index(root, split, info)
    (root / layout.PREPARING_FILE).unlink(missing_ok=True)
    return Summary(
        name=name,
        root=root,
        split=split,
        rule=rule,
        written=written,
        skipped=skipped,
        frames=sum(kept.values()),
        points=sum(kept.values()) * points,
        seconds=time.perf_counter() - begin,
        left_out=left_out,
        source=source,
    )
