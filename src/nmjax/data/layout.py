"""The on-disk format of a dataset, both directions: where it lives, its splits, its file names.

    <root>/<split>/vertices/<seq>.npy   (T, N, 3) float32 points of one sequence
    <root>/<split>/joints/<seq>.npy     (T, J, 3) ground-truth joints (optional; HanCo names them
                                        <seq>_joints.npy, see `JOINT_FILE_PATTERNS`)
    <root>/<split>/<kind>/<seq>.npy     further per-frame arrays (the synthetic sets: angles)
    <root>/split.json                   optional: {"train": [seq, ...], "test": [seq, ...]}
    <root>/meta.json                    optional: joint_names, parents (the true tree; its
                                        root -1, 2**32 - 1 or its own index), sample_rate, ...;
                                        a capture's (`capture_meta`) also up, fps, units and
                                        metres_per_unit; written last, so that it marks a
                                        finished set
    <root>/preparing.json               only while `nmjax prepare-data` has not finished: the
                                        settings a rerun must repeat to continue

A set may also keep all its sequences in `<root>/vertices/` (and `<root>/joints/`) without split
folders; `split_by_frames` then divides them 9:1. `<root>` defaults to `data/<name>` relative to
the working directory, or `$NMJAX_DATA/<name>` when the environment variable is set.

A user's own capture is prepared under the generic spec `capture` (`nmjax.config.DATASETS`); its
meta.json names the spec (`name`) and records the capture's up axis, frame rate and units, which
every command reading the set takes from there (`training_config`). A single sequence is cut in
two for a test split; meta.json's `cut_from` says which frames of it each part holds.

The readers (`nmjax.data.datasets`) and the writers (`nmjax.data.prepare`, the synthetic
generator `nmjax.data.synthetic`) all go through this module, so they cannot disagree.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
import shutil
from pathlib import Path

import numpy as np

from nmjax import atomic
from nmjax.config import DATASETS, SkelTrainConfig, dataset_spec, skel_preset
from nmjax.parents import parents_from_external

SPLITS = ("train", "test")
TEST_FRACTION = 0.1  # the 9:1 split
SYNTHETIC_DATASETS = tuple(name for name, spec in DATASETS.items() if spec.synthetic)

# How each dataset names its ground-truth joint files inside <split>/joints/.
JOINT_FILE_PATTERNS: dict[str, str] = {name: "{seq}.npy" for name in DATASETS}
JOINT_FILE_PATTERNS["hanco"] = "{seq}_joints.npy"

# Marks a real set whose preparation has not finished (see `nmjax.data.streaming`).
PREPARING_FILE = "preparing.json"

# The sequence names `split_names` gives; a generator may delete such files it did not write.
GENERATED_NAME = re.compile(r"seq_\d+")


def dataset_root(name: str, root: str | os.PathLike | None = None) -> Path:
    """Folder of dataset `name`: `root` if given, else `$NMJAX_DATA/<name>`, else `data/<name>`.

    Raises:
      ValueError: `name` is not a registered dataset (the message lists the valid ones).
    """
    dataset_spec(name)
    if root is not None:
        return Path(root)
    base = os.environ.get("NMJAX_DATA")
    return Path(base) / name if base else Path("data") / name


# --- a user's capture ------------------------------------------------------------------------

CAPTURE = "capture"  # the generic spec of a user's own capture
UP_AXES = ("x", "y", "z")
# Metres per unit of the lengths a capture may be given in (`--units`).
UNITS: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "ft": 0.3048}
DEFAULT_UP, DEFAULT_UNITS = "z", "m"  # nmjax's own bodies are z up; glTF's unit is the metre


def capture_meta(up: str | None = None, fps: float | None = None, units: str | None = None):
    """The meta.json entries of a user's capture: its up axis ("x" / "y" / "z", default z),
    frames per second (default the `capture` spec's, 30) and length unit (default m), with the
    metres per unit.

    Raises:
      ValueError: an unknown axis or unit, or fps not > 0 (naming the option).
    """
    up = DEFAULT_UP if up is None else up
    units = DEFAULT_UNITS if units is None else units
    fps = dataset_spec(CAPTURE).fps if fps is None else float(fps)
    if up not in UP_AXES:
        raise ValueError(f"--up must be one of {', '.join(UP_AXES)}, got {up!r}")
    if units not in UNITS:
        raise ValueError(f"--units must be one of {', '.join(UNITS)}, got {units!r}")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"--fps must be > 0, got {fps}")
    return {"up": up, "fps": fps, "units": units, "metres_per_unit": UNITS[units]}


def recorded_data_fields(meta: dict, where: str) -> dict:
    """The `DataConfig` fields a set's meta.json records: "up_axis" (0/1/2) from `up` and "fps"
    from `fps`, each where present.

    Raises:
      ValueError naming `where`: an `up` that is not x / y / z, an `fps` that is not > 0.
    """
    if not isinstance(meta, dict):
        raise ValueError(f"{where}: expected a JSON object, got {type(meta).__name__}")
    fields = {}
    if "up" in meta:
        if meta["up"] not in UP_AXES:
            axes = ", ".join(UP_AXES)
            raise ValueError(f"{where}: `up` must be one of {axes}, got {meta['up']!r}")
        fields["up_axis"] = UP_AXES.index(meta["up"])
    if "fps" in meta:
        fps = meta["fps"]
        if isinstance(fps, bool) or not isinstance(fps, int | float) or not fps > 0:
            raise ValueError(f"{where}: `fps` must be a number > 0, got {fps!r}")
        fields["fps"] = float(fps)
    return fields


def prepared_name(root: str | os.PathLike) -> str:
    """The dataset spec a prepared folder was written for: its meta.json's `name`.

    Raises:
      FileNotFoundError: `root` holds no meta.json (no finished preparation).
      ValueError: meta.json names no registered spec.
    """
    path = Path(root) / "meta.json"
    if not path.is_file():
        raise FileNotFoundError(
            f"{root} holds no prepared dataset (no meta.json); prepare your capture with `nmjax "
            f"prepare-data --from RAW --root {root}`, or name a dataset with --data"
        )
    meta = read_meta_file(path)
    name = meta.get("name") if isinstance(meta, dict) else None
    if name not in DATASETS:
        raise ValueError(
            f"{path} names no dataset spec (`name`: {name!r}); give --data NAME (one of "
            f"{', '.join(sorted(DATASETS))})"
        )
    return name


def training_config(
    name: str | None = None, root: str | os.PathLike | None = None, preset: str = "default"
) -> SkelTrainConfig:
    """The phase-1 preset of a prepared set: dataset `name` (default: the one `root`'s meta.json
    names, `prepared_name`), reading `root` when given, with the up axis and frame rate that the
    set's meta.json records (`recorded_data_fields`; a capture records both).

    Raises:
      FileNotFoundError, ValueError: as `prepared_name` and `recorded_data_fields`; neither
        `name` nor `root` given.
    """
    if name is None:
        if root is None:
            raise ValueError("training_config needs a dataset name or a prepared folder")
        name = prepared_name(root)
    cfg = skel_preset(name, preset)
    folder = dataset_root(name, root)
    fields = recorded_data_fields(read_meta(name, root), str(folder / "meta.json"))
    if root is not None:
        fields["root"] = str(root)
    return dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, **fields))


# --- splits -------------------------------------------------------------------------------------


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


def split_names(num_sequences: int) -> dict[str, list[str]]:
    """Names of a generated set per split: seq_000, seq_001, ...; the last max(1, round(n / 10))
    are the test split."""
    if num_sequences < 2:
        raise ValueError(
            f"num_sequences must be at least 2 (one train, one test), got {num_sequences}"
        )
    names = [f"seq_{i:03d}" for i in range(num_sequences)]
    num_test = max(1, round(num_sequences / 10))
    return {"train": names[:-num_test], "test": names[-num_test:]}


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


# --- reading --------------------------------------------------------------------------------------


def sequence_files(root: Path) -> dict[str, tuple[Path, Path]]:
    """seq name -> (vertices file, joints folder) over <root>/vertices and <root>/<split>/.

    Raises:
      ValueError: a sequence name appears in two folders.
    """
    found: dict[str, tuple[Path, Path]] = {}
    for folder in [root, *(root / s for s in SPLITS)]:
        for path in sorted((folder / "vertices").glob("*.npy")):
            if path.stem in found:
                raise ValueError(
                    f"sequence {path.stem!r} appears twice: {found[path.stem][0]} and {path}"
                )
            found[path.stem] = (path, folder / "joints")
    return found


def joints_file(name: str, joints_folder: Path, seq: str) -> Path | None:
    """The joints file of sequence `seq` of dataset `name` in `joints_folder`, or None.

    The dataset's own pattern (`JOINT_FILE_PATTERNS`) is tried first, then plain `<seq>.npy`.
    """
    for candidate in dict.fromkeys([JOINT_FILE_PATTERNS[name].format(seq=seq), f"{seq}.npy"]):
        if (joints_folder / candidate).is_file():
            return joints_folder / candidate
    return None


def read_meta(name: str, root: str | os.PathLike | None = None) -> dict:
    """`<root>/meta.json` of a dataset as a dict (`read_meta_file`), {} when it has none."""
    path = dataset_root(name, root) / "meta.json"
    return read_meta_file(path) if path.is_file() else {}


def read_meta_file(path: str | os.PathLike) -> dict:
    """A meta.json (a dataset's, or the one a raw source brings) as a dict, its `parents`, when it
    has them, a tree with the root its own parent whatever convention the file used
    (`nmjax.parents.parents_from_external`).

    Raises:
      ValueError: invalid JSON, or `parents` that are not a tree (naming the file and the entry).
    """
    path = Path(path)
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: invalid JSON ({err})") from err
    if isinstance(meta, dict) and meta.get("parents") is not None:
        meta["parents"] = parents_from_external(meta["parents"], f"{path} `parents`").tolist()
    return meta


def is_complete(root: str | os.PathLike) -> bool:
    """True when `root` holds a finished generated set: meta.json says "complete": true."""
    try:
        meta = json.loads((Path(root) / "meta.json").read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return False
    return isinstance(meta, dict) and meta.get("complete") is True


# --- writing --------------------------------------------------------------------------------------


def write_sequence(
    root: Path, split: str, seq: str, *, joint_file: str = "{seq}.npy", **arrays: np.ndarray | None
) -> None:
    """Writes one sequence into the layout, atomically, in the order the arrays are given.

    Every array `kind=array` goes to `<root>/<split>/<kind>/<seq>.npy` (kinds: vertices, joints,
    angles, ...); joints go to `<root>/<split>/joints/<joint_file>` with `{seq}` filled in (the
    dataset's `JOINT_FILE_PATTERNS` entry). Arrays given as None are skipped.
    """
    for kind, array in arrays.items():
        if array is not None:
            file = joint_file.format(seq=seq) if kind == "joints" else f"{seq}.npy"
            atomic.save_npy(root / split / kind / file, array)


def clear_dataset(root: Path) -> None:
    """Removes a previous dataset's files (only the nmjax layout, nothing else) from `root`."""
    for split in SPLITS:
        for sub in ("vertices", "joints"):
            if (root / split / sub).is_dir():
                shutil.rmtree(root / split / sub)
    for name in ("meta.json", "split.json", PREPARING_FILE):
        (root / name).unlink(missing_ok=True)


def write_index(root: Path, split: dict[str, list[str]], meta: dict) -> None:
    """Writes `<root>/split.json`, then `<root>/meta.json`: meta last marks the set complete."""
    atomic.write_json(root / "split.json", split)
    atomic.write_json(root / "meta.json", meta)
