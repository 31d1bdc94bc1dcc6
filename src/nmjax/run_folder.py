"""The run folder, written and read in one place (contract C10).

A phase-1 run (`nmjax train-skel`) holds

    config.json                 the `SkelTrainConfig` it trained with (`prepare_run_dir`)
    checkpoints/<step>/         orbax checkpoints (`nmjax.train.checkpoints`)
    metrics.jsonl, tb/          the metric log (`nmjax.train.metric_log`)
    figures/                    validation pictures, the skeleton's drawing
    affinity.npy                (N, K, K) the trained affinity         } `write_phase1_artifacts`,
    keypoint_stats.npz          `STATS_KEYS`, see `read_skeleton_inputs`} when training ends
    skeleton.json               Algorithm 1's tree (`write_skeleton`)
    keypoints_<split>.npz       {sequence: (T_seq, K, 4)} (`write_trajectories`)
    refined/<split>/<seq>.npz   optional: a sequence's refined skeleton (`nmjax refine`,
                                `write_refined`; `REFINED_KEYS`)

and a phase-2 run (`nmjax train-dyn`) config.json (a `DynTrainConfig` whose `skel_run` names its
phase-1 run), checkpoints/, metrics.jsonl, tb/ and figures/.

Runs live under `RUNS_ROOT` unless a config names its folder; `default_run_dir` names a new one
`<phase>-<data>[-<model>]-<UTC time>`, and `find_skel_run` finds the latest phase-1 run of a
dataset by that name. A folder that holds anything is never reused unless the run resumes or
overwrites it (`check_run_dir`).

Nothing here runs a model: loading a trained network from a folder is
`nmjax.train.trained`'s.
"""

from __future__ import annotations

import datetime
import json
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from nmjax import atomic
from nmjax.config import SkelTrainConfig, frame_rate
from nmjax.config_io import config_from_dict, config_to_dict, flatten_config
from nmjax.skeleton import Skeleton, load_skeleton, skeleton_from_parents

# --- names --------------------------------------------------------------------------------------

RUNS_ROOT = Path("runs")
SPLITS = ("train", "test")

# Both phases: written when the run starts and as it trains.
CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.jsonl"
TENSORBOARD_DIR = "tb"
CHECKPOINTS = "checkpoints"
FIGURES_DIR = "figures"
# Phase 1: the inputs of skeleton extraction, written when training ends ...
AFFINITY_FILE = "affinity.npy"
STATS_FILE = "keypoint_stats.npz"
STATS_KEYS = ("intensities", "rest_positions", "example_voxels", "example_keypoints")
# ... and what follows from them: the skeleton and each split's keypoints.
SKELETON_FILE = "skeleton.json"
# Optional, after phase 1: the articulated refinement of a sequence's skeleton (`nmjax refine`,
# `nmjax.skeleton_refine`), one file per split and sequence under REFINED_DIR.
REFINED_DIR = "refined"
# What a refined file holds: the kept joints (keypoint indices, J) and their tree (J,) as in
# `nmjax.export.rig.kept_tree`; the rest pose (J, 3) and the rest offsets (J, 3); per frame the
# local and world rotations (T, J, 3, 3), the joint positions (T, J, 3) and the root (T, 3);
# the rest surface (V, 3) and its skin weights (V, J); the sequence's normalisation factor (the
# `box_scale` of p' = s (p - bmin) - 1); the objective's Chamfer term at every iteration; and
# the settings as a JSON string.
REFINED_KEYS = (
    "joints",
    "parents",
    "rest_positions",
    "offsets",
    "local_rotations",
    "rotations",
    "positions",
    "root",
    "surface",
    "weights",
    "box_scale",
    "chamfer_history",
    "settings",
)


def keypoints_file(run: str | Path, split: str) -> Path:
    """`<run>/keypoints_<split>.npz`: the frozen detector's keypoints of every sequence."""
    return Path(run) / f"keypoints_{split}.npz"


def checkpoint_dir(run: str | Path) -> Path:
    """`<run>/checkpoints`, where `nmjax.train.checkpoints.Checkpointer` keeps the steps."""
    return Path(run) / CHECKPOINTS


def default_run_dir(phase: str, data: str, model: str | None = None) -> Path:
    """A new run's folder: `RUNS_ROOT/<phase>-<data>[-<model>]-<UTC yyyymmdd-hhmmss>`.

    Args:
      phase: "skel" or "dyn".
      data: the dataset name.
      model: phase 2's model kind ("nm", "vrnn"), part of the name so both can train at once.
    """
    stamp = datetime.datetime.now(datetime.UTC).strftime("%Y%m%d-%H%M%S")
    return RUNS_ROOT / "-".join([phase, data, *([model] if model else []), stamp])


def config_run_dir(run: str | None, phase: str, data: str, model: str | None = None) -> Path:
    """The folder a config's `run` names, else a new `default_run_dir(phase, data, model)`: how
    both phases' entries choose their run folder."""
    return Path(run) if run else default_run_dir(phase, data, model)


def find_skel_run(
    data: str, skel_run: str | Path | None = None, runs_root: str | Path = RUNS_ROOT
) -> Path:
    """The phase-1 run to train on: `skel_run`, or the latest `runs_root/skel-<data>-*` folder
    (`default_run_dir`'s names sort by time).

    Raises:
      FileNotFoundError: no such run, naming the command that creates it.
    """
    if skel_run is not None:
        path = Path(skel_run)
        if not path.is_dir():
            raise FileNotFoundError(
                f"--skel-run {path} does not exist; train phase 1 first with "
                f"`make train-skel DATA={data}` or pass an existing phase-1 run folder"
            )
        return path
    candidates = sorted(p for p in Path(runs_root).glob(f"skel-{data}-*") if p.is_dir())
    if not candidates:
        raise FileNotFoundError(
            f"no phase-1 run of {data!r} under {runs_root}/ (expected {runs_root}/skel-{data}-*); "
            f"run `make train-skel DATA={data}` first, or pass --skel-run DIR"
        )
    return candidates[-1]


# --- config.json and the refuse-to-reuse rule ---------------------------------------------------

# Fields that say where a run and its data live, not what it computes (dotted as
# `flatten_config` spells them): two runs that differ only in them trained the same thing
# (`nmjax.rows` compares results rows without them).
LOCATION_FIELDS = frozenset({"run", "data.root"})
# Fields a resumed run may change: where it lives, how long it trains and what it reports, not
# what it computes.
RESUMABLE_FIELDS = LOCATION_FIELDS | frozenset(
    {
        "loop.steps",
        "loop.log_every",
        "loop.val_every",
        "loop.ckpt_every",
        "loop.keep_every",
        "loop.time_limit_minutes",
    }
)


def load_config(run: str | Path, cls: type) -> Any:
    """Reads `<run>/config.json` back into the dataclass `cls` (`config.config_from_dict`, which
    also reads the flat layout of runs made before the shared groups were nested)."""
    file = Path(run) / CONFIG_FILE
    if not file.is_file():
        raise FileNotFoundError(f"{file} not found; is {run} a run folder written by nmjax?")
    try:
        data = json.loads(file.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{file} is not valid JSON ({err}); the run folder is damaged") from err
    return config_from_dict(cls, data, source=str(file))


def run_kind(run: str | Path) -> str:
    """ "dyn" for a phase-2 run folder (its config names a `skel_run`), "skel" for phase 1."""
    path = Path(run) / CONFIG_FILE
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} not found; --run must be a run folder of `nmjax train-skel` or "
            "`nmjax train-dyn`"
        )
    try:
        config = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path} is not valid JSON ({err}); the run folder is damaged") from err
    return "dyn" if "skel_run" in config else "skel"


def checkpoint_steps(run: str | Path) -> list[int]:
    """The complete checkpoint steps of the run folder `run`, without creating or cleaning
    anything.

    Orbax writes a step into a temporary folder and renames it when the save is complete, so a
    process killed mid-save leaves only a `<step>.orbax-checkpoint-tmp-*` folder, which is not a
    step here (the next `Checkpointer` removes it).
    """
    directory = checkpoint_dir(run)
    if not directory.is_dir():
        return []
    return sorted(int(p.name) for p in directory.iterdir() if p.is_dir() and p.name.isdigit())


def check_resume_config(saved: Any, config: Any, path: str | Path) -> None:
    """Refuses (ValueError naming the fields) a resume whose config changes more than
    `RESUMABLE_FIELDS` of the run's saved one."""
    old, new = flatten_config(saved), flatten_config(config)
    changed = sorted(
        k for k in old.keys() | new.keys() if old.get(k) != new.get(k) and k not in RESUMABLE_FIELDS
    )
    if changed:
        diffs = ", ".join(f"{k} (run: {old.get(k)!r}, asked: {new.get(k)!r})" for k in changed)
        raise ValueError(
            f"--resume continues {path} with its own configuration, but the command changes "
            f"{diffs}; drop those options (only --steps and the log/val/checkpoint cadence may "
            "change) or start a new run with --run"
        )


def _holds_anything(path: Path) -> bool:
    return path.exists() and (not path.is_dir() or any(path.iterdir()))


def check_run_dir(path: str | Path, *, resume: bool, config: Any, overwrite: bool = False) -> None:
    """Every refusal `prepare_run_dir` can make, without writing anything.

    With `resume` the folder must hold a config.json that `config` differs from only in
    `RESUMABLE_FIELDS`, and at least one complete checkpoint.

    Raises:
      FileNotFoundError: `resume` and the folder, its config.json or its checkpoints are missing.
      ValueError: the folder exists and holds files, and neither `resume` nor `overwrite` is set;
        or `resume` with a configuration that changes what the run computes, or of a folder
        whose only checkpoint is an import's step 0 (pointing to --init-from).
    """
    path = Path(path)
    if not resume:
        if _holds_anything(path) and not overwrite:
            raise ValueError(
                f"run folder {path} already exists; pass --resume to continue it, --overwrite to "
                "replace it, or choose another --run"
            )
        return
    if not path.is_dir():
        raise FileNotFoundError(
            f"cannot resume: run folder {path} does not exist; drop --resume to start a new run"
        )
    check_resume_config(load_config(path, type(config)), config, path)
    steps = checkpoint_steps(path)
    if not steps:
        raise FileNotFoundError(
            f"cannot resume {path}: it has no complete checkpoint; start it again with "
            "--overwrite (or drop --resume with a new --run)"
        )
    if steps == [0]:
        # Only `nmjax import-release` writes a step 0: weights with an optimizer state that no
        # step has touched. Resuming would train the imported folder itself, in place.
        raise ValueError(
            f"cannot resume {path}: it holds imported weights (checkpoint 0) and no optimizer "
            f"state of a training run; fine-tune them in a new run with --init-from {path}"
        )


def prepare_run_dir(
    path: str | Path, *, resume: bool, config: Any, overwrite: bool = False
) -> Path:
    """Creates (or reopens, with `resume`) a run folder and writes `config.json` into it.

    Nothing is written before every check of `check_run_dir` has passed.

    Args:
      path: the run folder.
      resume: continue an existing run; the folder must hold a checkpoint and a config that
        `config` changes only in `RESUMABLE_FIELDS`.
      config: a dataclass; `config.config_to_dict(config)` is written to `<path>/config.json`.
      overwrite: delete an existing folder and start afresh (ignored with `resume`).

    Returns:
      The run folder as a Path.

    Raises:
      FileNotFoundError, ValueError: see `check_run_dir`.
    """
    path = Path(path)
    check_run_dir(path, resume=resume, config=config, overwrite=overwrite)
    if not resume and _holds_anything(path):
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink()
    path.mkdir(parents=True, exist_ok=True)
    atomic.write_json(path / CONFIG_FILE, config_to_dict(config))
    return path


# --- phase 1: the artefacts of training, the skeleton, the keypoints -----------------------------


def write_phase1_artifacts(
    run: str | Path, affinity: Any, keypoints: Any, example_voxels: Any
) -> None:
    """affinity.npy and keypoint_stats.npz: what skeleton extraction reads (`read_skeleton_inputs`).

    Args:
      run: the phase-1 run folder.
      affinity: (N, K, K) the trained affinity matrices.
      keypoints: (..., K, 4) the detector's keypoints over some frames of the data (validation
        crops when training ends; a motion's frames when a released model is imported); the
        statistics are taken over all leading axes, the first frame is the drawn example.
      example_voxels: (G, G, G) the voxels of that first frame, drawn under the skeleton.
    """
    run = Path(run)
    keypoints = np.asarray(keypoints, np.float32)
    flat = keypoints.reshape(-1, *keypoints.shape[-2:])  # (frames, K, 4)
    atomic.save_npy(run / AFFINITY_FILE, np.asarray(affinity, np.float32))
    atomic.save_npz(
        run / STATS_FILE,
        intensities=flat[:, :, 3].mean(axis=0),
        rest_positions=flat[:, :, :3].mean(axis=0),
        example_voxels=np.asarray(example_voxels, np.float32),
        example_keypoints=flat[0],
    )


def read_skeleton_inputs(run: str | Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(affinity (N, K, K), keypoint stats) of a phase-1 run, checked against each other.

    The stats are {"intensities": (K,) mean alpha, "rest_positions": (K, 3) mean position,
    "example_voxels": (G, G, G), "example_keypoints": (K, 4) of that frame}.

    Raises:
      FileNotFoundError: a missing run folder or file (names the file and how it is made).
      ValueError: missing keys or shapes that disagree.
    """
    run = Path(run)
    if not run.is_dir():
        raise FileNotFoundError(f"phase-1 run folder {run} does not exist (--run)")
    affinity_path, stats_path = run / AFFINITY_FILE, run / STATS_FILE
    for path in (affinity_path, stats_path):
        if not path.is_file():
            raise FileNotFoundError(
                f"{path} not found; phase-1 training (`nmjax train-skel`) writes it at the end"
            )
    affinity = np.load(affinity_path)
    if affinity.ndim == 2:
        affinity = affinity[None]
    if affinity.ndim != 3 or affinity.shape[1] != affinity.shape[2]:
        raise ValueError(f"{affinity_path} must hold an (N, K, K) array, got {affinity.shape}")
    num = affinity.shape[1]
    with np.load(stats_path) as z:
        missing = [k for k in STATS_KEYS if k not in z.files]
        if missing:
            raise ValueError(f"{stats_path} lacks {missing}; it needs {list(STATS_KEYS)}")
        stats = {k: np.asarray(z[k]) for k in STATS_KEYS}
    expected = {
        "intensities": (num,),
        "rest_positions": (num, 3),
        "example_keypoints": (num, 4),
    }
    for key, shape in expected.items():
        if stats[key].shape != shape:
            raise ValueError(
                f"{stats_path}: {key} has shape {stats[key].shape}, expected {shape} for the "
                f"K={num} keypoints of {affinity_path}"
            )
    if stats["example_voxels"].ndim != 3:
        raise ValueError(
            f"{stats_path}: example_voxels must be (G, G, G), got {stats['example_voxels'].shape}"
        )
    return affinity, stats


def write_skeleton(run: str | Path, skeleton: Skeleton, **extras: Any) -> Path:
    """`<run>/skeleton.json`: the tree plus `extras` (`Skeleton.save`); `extract_run_skeleton`
    stores the intensities, the extraction's options, `pruned_parents` and `keep` there."""
    path = Path(run) / SKELETON_FILE
    skeleton.save(path, **extras)
    return path


def read_skeleton(run: str | Path) -> Skeleton:
    """The tree of a phase-1 run's `skeleton.json` (the one reader of that file).

    Raises:
      FileNotFoundError: the skeleton has not been extracted yet (names the command).
      ValueError: the file is not JSON, lacks `parents` or they do not describe a rooted tree.
    """
    path = Path(run) / SKELETON_FILE
    fix = f"re-run `nmjax extract-skeleton --run {run}`"
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} not found; extract the skeleton first with `nmjax extract-skeleton --run "
            f"{run}`"
        )
    try:
        return load_skeleton(path)
    except (json.JSONDecodeError, TypeError) as err:
        raise ValueError(f"{path} is not a skeleton file ({err}); {fix}") from err
    except ValueError as err:
        raise ValueError(f"{err}; {fix}") from err


def skeleton_intensities(run: str | Path) -> np.ndarray | None:
    """The mean keypoint intensities stored beside the tree in skeleton.json, if any."""
    values = json.loads((Path(run) / SKELETON_FILE).read_text()).get("intensities")
    return None if values is None else np.asarray(values, np.float64)


def pruned_skeleton(run: str | Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(pruned parents (K,), kept-node mask (K,) bool) exactly as `extract_run_skeleton` stored
    them in the run's skeleton.json (`pruned_parents`, `keep`), or None when the run has no
    skeleton.json.

    Nothing is pruned again: these are the nodes the run's skeleton keeps, whatever threshold
    it was extracted with (`nmjax extract-skeleton --prune-threshold`).

    Raises:
      ValueError: the file lacks the two fields, or they do not describe a tree over the kept
        nodes with the root kept (names the command that rewrites the file).
    """
    path = Path(run) / SKELETON_FILE
    if not path.is_file():
        return None
    tree = read_skeleton(run)
    stored = json.loads(path.read_text())
    fix = f"re-run `nmjax extract-skeleton --run {run}`"
    if "keep" not in stored or "pruned_parents" not in stored:
        raise ValueError(f"{path} lacks `keep` / `pruned_parents` (the kept nodes); {fix}")
    keep = np.asarray(stored["keep"])
    try:
        pruned = skeleton_from_parents(np.asarray(stored["pruned_parents"]))
    except ValueError as err:
        raise ValueError(f"{path}: `pruned_parents` is not a tree ({err}); {fix}") from err
    parents = np.asarray(pruned.parents)
    if (
        keep.dtype != bool
        or keep.shape != (tree.num_keypoints,)
        or pruned.num_keypoints != tree.num_keypoints
        or not keep[pruned.root]
        or not keep[parents[keep]].all()
    ):
        raise ValueError(
            f"{path}: `keep` and `pruned_parents` must be {tree.num_keypoints} booleans and a "
            f"tree over the same keypoints whose kept nodes hang off kept nodes; {fix}"
        )
    return parents, keep


def write_trajectories(path: str | Path, trajectories: Mapping[str, Any]) -> Path:
    """A keypoints .npz (the layout of keypoints_<split>.npz, `keypoints_file`): one float32
    (T_seq, K, 4) array per sequence name."""
    path = Path(path)
    atomic.save_npz(path, **{k: np.asarray(v, np.float32) for k, v in trajectories.items()})
    return path


def load_trajectories(run: str | Path, split: str) -> dict[str, np.ndarray]:
    """Keypoint trajectories {sequence: (T_seq, K, 4) float32} of a phase-1 run's split.

    Raises:
      FileNotFoundError: keypoints_<split>.npz has not been exported (names the command).
    """
    path = keypoints_file(run, split)
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} not found; export the phase-1 keypoints first with "
            f"`nmjax export-keypoints --run {run}`"
        )
    return read_trajectories(path)


def read_trajectories(path: str | Path) -> dict[str, np.ndarray]:
    """{sequence: (T_seq, K, 4) float32} of a keypoints .npz (the layout of keypoints_*.npz).

    Raises:
      ValueError: no sequences, a wrong shape, or values that are not finite in float32.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found; export it with `nmjax export-keypoints`")
    with np.load(path) as npz:
        raw = {name: np.asarray(npz[name]) for name in npz.files}
    if not raw:
        raise ValueError(f"{path} holds no sequences; re-export the keypoints")
    trajectories = {}
    for name, x in raw.items():
        if x.ndim != 3 or x.shape[-1] != 4:
            raise ValueError(f"{path}[{name!r}] has shape {x.shape}; expected (T_seq, K, 4)")
        with np.errstate(over="ignore", invalid="ignore"):
            x32 = x.astype(np.float32)
        if not np.isfinite(x32).all():
            raise ValueError(
                f"{path}[{name!r}] holds NaN, inf or values beyond the float32 range; re-export "
                "the keypoints"
            )
        trajectories[name] = x32
    return trajectories


# --- phase 1, optional: refined skeletons ---------------------------------------------------------


def refined_file(run: str | Path, split: str, seq: str) -> Path:
    """`<run>/refined/<split>/<seq>.npz`: the refined skeleton of one sequence (`REFINED_KEYS`)."""
    return Path(run) / REFINED_DIR / split / f"{seq}.npz"


def write_refined(run: str | Path, split: str, seq: str, arrays: Mapping[str, Any]) -> Path:
    """Writes one sequence's refined skeleton atomically (every key of `REFINED_KEYS`; "settings"
    a JSON string), replacing an earlier refinement of it.

    Raises:
      ValueError: a key missing or unknown.
    """
    if set(arrays) != set(REFINED_KEYS):
        raise ValueError(
            f"a refined skeleton holds {', '.join(REFINED_KEYS)}; got {', '.join(sorted(arrays))}"
        )
    path = refined_file(run, split, seq)
    out = {k: np.asarray(v) for k, v in arrays.items() if k != "settings"}
    atomic.save_npz(path, **out, settings=np.asarray(str(arrays["settings"])))
    return path


def refined_sequences(run: str | Path, split: str) -> list[str]:
    """The sequences of `split` that hold a refined skeleton, sorted."""
    folder = Path(run) / REFINED_DIR / split
    return sorted(p.stem for p in folder.glob("*.npz")) if folder.is_dir() else []


def read_refined(run: str | Path, split: str, seq: str) -> dict[str, Any] | None:
    """One sequence's refined skeleton ({key of `REFINED_KEYS`: array}, "settings" a dict), or
    None when the sequence has none.

    Raises:
      ValueError: a damaged file (missing keys, shapes that disagree), naming the command that
        writes it again.
    """
    path = refined_file(run, split, seq)
    if not path.is_file():
        return None
    fix = f"refine it again with `nmjax refine --run {run} --split {split} --seq {seq}`"
    try:
        with np.load(path) as z:
            arrays = {k: np.asarray(z[k]) for k in z.files}
    except (OSError, ValueError, EOFError) as err:
        raise ValueError(f"{path} is not a refined skeleton ({err}); {fix}") from err
    missing = [k for k in REFINED_KEYS if k not in arrays]
    if missing:
        raise ValueError(f"{path} lacks {', '.join(missing)}; {fix}")
    num, frames = len(arrays["joints"]), len(arrays["positions"])
    verts = len(arrays["surface"])
    expected = {
        "joints": (num,),
        "parents": (num,),
        "rest_positions": (num, 3),
        "offsets": (num, 3),
        "local_rotations": (frames, num, 3, 3),
        "rotations": (frames, num, 3, 3),
        "positions": (frames, num, 3),
        "root": (frames, 3),
        "surface": (verts, 3),
        "weights": (verts, num),
        "box_scale": (),
    }
    wrong = [
        f"{k} {arrays[k].shape} (expected {v})" for k, v in expected.items() if arrays[k].shape != v
    ]
    if wrong:
        raise ValueError(f"{path}: {'; '.join(wrong)}; {fix}")
    try:
        arrays["settings"] = json.loads(str(arrays["settings"]))
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: its settings are not JSON ({err}); {fix}") from err
    return arrays


def motion_format(run: str | Path) -> tuple[float, int]:
    """(frames per second, up axis 0/1/2) of a phase-1 run's keypoint sequences, from its data
    configuration (`config.frame_rate`: its recorded `fps`, else the dataset's)."""
    data = load_config(run, SkelTrainConfig).data
    return frame_rate(data.name, data.sample_rate, data.fps), data.up_axis
