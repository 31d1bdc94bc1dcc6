"""Trained models out of run folders, for the tasks and evaluations: the phase-1 detector's
inference over whole sequences and the keypoint export (`export_keypoints`), the artefacts that
end phase 1 (`finish_phase1`), skeleton extraction (`extract_run_skeleton`), the phase-2 model
(`restore_dynamics`, `load_phase2`, `phase2_runs`).

What a run folder holds, its file names and the readers and writers of each file are
`nmjax.run_folder`'s (contract C10). The restored detector (`nmjax.train.skel.Detector`) and
what phase 2 is fed (`nmjax.train.dyn_inputs`) sit with the trainers below, which build on them.

Nothing here runs a model or writes a file as a side effect of reading: a missing export is an
error naming the command that makes it.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from nmjax.config import DynTrainConfig
from nmjax.data.datasets import pad_with_last
from nmjax.models.dynamics import Dynamics
from nmjax.run_folder import (
    CONFIG_FILE,
    FIGURES_DIR,
    SPLITS,
    checkpoint_steps,
    keypoints_file,
    load_config,
    read_skeleton,
    read_skeleton_inputs,
    write_skeleton,
    write_trajectories,
)
from nmjax.skeleton import (
    DEFAULT_NEIGHBORS,
    PRUNE_THRESHOLD,
    Skeleton,
    extract_skeleton,
    prune,
)
from nmjax.train import dyn, parallel
from nmjax.train.skel import Detector

# --- phase 1: the detector --------------------------------------------------------------------


def sequence_points(seq, sample_rate: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (S, N, 3) and ground-truth joints (S, J, 3) (None without) of every
    `sample_rate`-th frame, normalised with one bounding box over the whole sequence: the frames
    `export_keypoints` detects on, in the keypoints' coordinates."""
    from nmjax.data.normalize import normalize_sequence

    joints = None if seq.joints is None else np.asarray(seq.joints[::sample_rate], np.float32)
    return normalize_sequence(np.asarray(seq.vertices[::sample_rate], np.float32), joints)


def sequence_voxels(seq, sample_rate: int, grid: int) -> np.ndarray:
    """(S, G, G, G): every `sample_rate`-th frame, one bounding box over the whole sequence."""
    from nmjax.data.voxelize import voxelize

    points, _ = sequence_points(seq, sample_rate)
    return voxelize(points, grid)


def sequence_windows(voxels: np.ndarray, frames: int) -> np.ndarray:
    """(S, G, G, G) -> (ceil(S / T), T, G, G, G); the last window padded with the last frame."""
    windows = -(-voxels.shape[0] // frames)
    voxels = pad_with_last(voxels, windows * frames)
    return voxels.reshape(windows, frames, *voxels.shape[1:])


def export_keypoints(
    run: str | Path,
    split: str,
    *,
    detector: Detector | None = None,
    data_root: str | Path | None = None,
    path: str | Path | None = None,
) -> Path:
    """Writes `<run>/keypoints_<split>.npz`: one (S, K, 4) array per sequence of the split.

    Each whole sequence (every `sample_rate`-th frame) is normalised with one bounding box
    (DESIGN section 4), voxelised, cut into consecutive windows of T frames (the last padded by
    repeating the last frame) and run through the detector in compiled batches of B windows.
    `data_root` reads the sequences from another copy of the run's dataset (e.g. a set of
    longer synthetic sequences), `path` writes the file elsewhere.
    """
    from nmjax.data.datasets import load_sequences

    run = Path(run)
    detector = Detector.load(run) if detector is None else detector
    data = detector.cfg.data
    arrays = {}
    for seq in load_sequences(data.name, split, data.root if data_root is None else data_root):
        voxels = sequence_voxels(seq, data.sample_rate, data.grid)
        keypoints = detector.keypoints(sequence_windows(voxels, data.frames))
        keypoints = keypoints.reshape(-1, *keypoints.shape[2:])  # windows joined in time
        arrays[seq.name] = keypoints[: len(voxels)].astype(np.float32)
    return write_trajectories(keypoints_file(run, split) if path is None else path, arrays)


def finish_phase1(run: str | Path, *, export: bool = True) -> None:
    """The artefacts phase 2 needs after training: skeleton.json and (with `export`)
    keypoints_{train,test}.npz.

    Both come from the run's best checkpoint by validation loss: the skeleton from the affinity
    `skel.train_skeleton` wrote of it, the keypoints from `Detector.load`'s detector, the one
    the release keeps and every later reader (tasks, evaluation, phase 2's "crop" inputs)
    restores. The last checkpoint may be a worse model that merely came later.

    Every host takes part in restoring the detector; only process 0 writes.
    """
    run = Path(run)
    if parallel.is_primary():
        try:
            extract_run_skeleton(run)
        except (ValueError, FileNotFoundError) as err:
            # The skeleton stage is separate; the training results stay valid.
            print(
                f"train-skel: skeleton extraction failed ({err}); run "
                f"`nmjax extract-skeleton --run {run}` once fixed",
                file=sys.stderr,
            )
    if export:
        detector = Detector.load(run)
        if parallel.is_primary():
            for split in SPLITS:
                export_keypoints(run, split, detector=detector)


# --- phase 1: the skeleton --------------------------------------------------------------------


def extract_run_skeleton(
    run: str | os.PathLike,
    n_neighbors: int | None = None,
    prune_threshold: float = PRUNE_THRESHOLD,
    method: str = "algorithm1",
) -> Skeleton:
    """Extracts, saves and draws the skeleton of a phase-1 run (`nmjax extract-skeleton`).

    Args:
      run: phase-1 run folder with affinity.npy and keypoint_stats.npz.
      n_neighbors: N of Algorithm 1; None uses `DEFAULT_NEIGHBORS` (2).
      prune_threshold: keypoints with mean intensity below it are drawn faded and listed as
        pruned (`pruned_parents`, `keep`); the tree itself spans all K keypoints.
      method: "algorithm1" (the paper's, default) or "filtered" (`extract_skeleton`).

    Returns:
      The `Skeleton` written to `<run>/skeleton.json`.
    """
    from nmjax import viz  # matplotlib only where a picture is drawn

    run = Path(run)
    n_neighbors = DEFAULT_NEIGHBORS if n_neighbors is None else n_neighbors
    affinity, stats = read_skeleton_inputs(run)
    skeleton = extract_skeleton(affinity, n_neighbors, stats["intensities"], method=method)
    pruned, keep = prune(skeleton, stats["intensities"], prune_threshold)
    write_skeleton(
        run,
        skeleton,
        intensities=stats["intensities"].astype(np.float64),
        rest_positions=stats["rest_positions"].astype(np.float64),
        n_neighbors=int(n_neighbors),
        method=method,
        prune_threshold=float(prune_threshold),
        pruned_parents=list(pruned.parents),
        keep=keep.tolist(),
    )
    viz.draw_skeleton(
        run / FIGURES_DIR / "skeleton.png",
        skeleton,
        stats["example_keypoints"],
        stats["example_voxels"],
        keep,
        title=f"{run.name}: K={skeleton.num_keypoints}, kept {int(keep.sum())}",
    )
    return skeleton


# --- phase 2 ----------------------------------------------------------------------------------


def restore_dynamics(run: str | Path, step: int | None = None) -> Dynamics:
    """The trained dynamics model of a phase-2 run folder (latest checkpoint by default)."""
    run = Path(run)
    cfg = load_config(run, DynTrainConfig)
    if not cfg.skel_run:
        raise ValueError(f"{run}/config.json names no skel_run; is {run} a `train-dyn` run?")
    skeleton = read_skeleton(cfg.skel_run)
    return dyn.restore_model(run, cfg, skeleton.parents, skeleton.order, step)


def load_phase2(run: str | Path) -> tuple[Dynamics, DynTrainConfig, Path]:
    """(dynamics model, its config, the phase-1 run folder) of a phase-2 run."""
    model = restore_dynamics(run)
    cfg = load_config(run, DynTrainConfig)
    return model, cfg, Path(cfg.skel_run)


def find_vrnn_run(dyn_run: Path, skel_run: Path, inputs: str = "crop") -> Path | None:
    """A positional-baseline phase-2 run beside `dyn_run` trained on the same phase-1 run with
    the same `inputs`."""
    for candidate in sorted(Path(dyn_run).parent.glob("*"), reverse=True):
        if candidate == Path(dyn_run) or not (candidate / CONFIG_FILE).is_file():
            continue
        try:
            cfg = load_config(candidate, DynTrainConfig)
        except (ValueError, FileNotFoundError, TypeError):
            continue
        same = cfg.skel_run and Path(cfg.skel_run).resolve() == Path(skel_run).resolve()
        same = same and cfg.inputs == inputs
        if cfg.model.model == "vrnn" and same and bool(checkpoint_steps(candidate)):
            return candidate
    return None


def phase2_runs(run: Path, vrnn_run: str | Path | None) -> tuple[DynTrainConfig, Path, Path | None]:
    """(config of the "nm" run, its phase-1 run, the VRNN run given or found beside it).

    Raises:
      ValueError: `run` is not an "nm" run, or the VRNN run was trained on another phase-1 run.
    """
    dyn_cfg = load_config(run, DynTrainConfig)
    if dyn_cfg.model.model != "nm":
        raise ValueError(
            f"{run} is a '{dyn_cfg.model.model}' run; give the Neural Marionette ('nm') run "
            "as --run and the positional baseline as --vrnn-run"
        )
    skel_run = Path(dyn_cfg.skel_run)
    if vrnn_run is None:
        return dyn_cfg, skel_run, find_vrnn_run(run, skel_run, dyn_cfg.inputs)
    vrnn_run = Path(vrnn_run)
    vrnn_cfg = load_config(vrnn_run, DynTrainConfig)
    vrnn_skel = vrnn_cfg.skel_run
    if not vrnn_skel or Path(vrnn_skel).resolve() != skel_run.resolve():
        raise ValueError(
            f"--vrnn-run {vrnn_run} was trained on the phase-1 run {vrnn_skel}, {run} on "
            f"{skel_run}; compare models of the same skeleton (train the baseline with "
            f"`nmjax train-dyn --model vrnn --skel-run {skel_run}`)"
        )
    if vrnn_cfg.inputs != dyn_cfg.inputs:
        raise ValueError(
            f"--vrnn-run {vrnn_run} was trained on inputs '{vrnn_cfg.inputs}', {run} on "
            f"'{dyn_cfg.inputs}'; both methods condition on the same keypoints, so train the "
            f"baseline with `nmjax train-dyn --model vrnn --skel-run {skel_run} --set "
            f"inputs={dyn_cfg.inputs}`"
        )
    return dyn_cfg, skel_run, vrnn_run
