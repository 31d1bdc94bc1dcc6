"""`nmjax refine`: the articulated refinement of a phase-1 run's skeleton, one sequence at a time
(the math is `nmjax.skeleton_refine`, docs/architecture.md §7b), and the rig `nmjax export`
reads back (`nmjax.export.sources.refined_rig`).

For every sequence of a split: the exported keypoints (keypoints_<split>.npz) and the dataset's
points of the same frames, normalised with the same box (`trained.sequence_points`); the
unrefined rig `nmjax export` builds from them (the kept nodes, rest pose frame 0, swing-only
rotations: `sources.positions_rig`) with Algorithm 2's weights on `surface_points` of frame 0's
points (`sources.kept_skin_weights`), which is where the fit starts; then `skeleton_refine.fit`.
The refined skeleton goes to `run_folder.refined_file` (atomically), which `nmjax export` and
`nmjax view` read. The run's skeleton.json and keypoints are left as they are.

`refine_run` is the library entry: `nmjax refine` calls it, and so can any command that makes a
rig and refines it (a rig command's refine option).
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from nmjax.export.rig import Rig
from nmjax.export.sources import kept_skin_weights, positions_rig
from nmjax.skeleton_refine import RefineSettings

# Points of every frame the reported fit error compares at most (a fixed subset, seed 0), as
# `nmjax evaluate`'s fit error does (`nmjax.evaluate.field_scores.FIT_POINTS`).
FIT_POINTS = 4096


@dataclasses.dataclass(frozen=True)
class RefinedSequence:
    """What refining one sequence did.

    Attributes:
      name: the sequence; path: the refined file written.
      frames, joints, points: the motion's frames, the kept joints, the rest surface's points.
      fit_before, fit_after: the rig's fit error (`metrics.rig_fit_error`, x1e4 in the cube) of
        the unrefined and the refined rig on the same rest surface and frames.
      seconds: the refinement's wall time (compilation included).
    """

    name: str
    path: Path
    frames: int
    joints: int
    points: int
    fit_before: float
    fit_after: float
    seconds: float


def point_subset(count: int, limit: int, seed: int = 0) -> np.ndarray:
    """All of `count` point indices up to `limit`, else `limit` of them drawn with `seed`, in
    increasing order."""
    if count <= limit:
        return np.arange(count)
    return np.sort(np.random.default_rng(seed).choice(count, limit, replace=False))


def unrefined_rig(
    name: str, keypoints: np.ndarray, skeleton: tuple[np.ndarray, np.ndarray], frame_rate: float
) -> Rig:
    """The rig `nmjax export` makes of a phase-1 run's keypoints (`sources.positions_rig`):
    skeleton = (pruned parents (K,), kept nodes (K,) bool)."""
    parents, keep = skeleton
    return positions_rig(name, keypoints, parents, keep, frame_rate)


def refine_sequence(
    keypoints: np.ndarray,
    points: np.ndarray,
    skeleton: tuple[np.ndarray, np.ndarray],
    box_scale: float,
    settings: RefineSettings | None = None,
    *,
    progress: bool = True,
    name: str = "sequence",
) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Refines one sequence's skeleton (module docstring).

    Args:
      keypoints: (T, K, 4) phase 1's keypoints; points: (T, N, 3) the sequence's points in the
        same cube; skeleton: (pruned parents (K,), kept nodes (K,) bool); box_scale: the
        sequence's normalisation factor (for the fit error in the capture's units).
      settings: the refinement's settings (default `RefineSettings()`); progress: a bar over the
        iterations; name: its label.

    Returns:
      (the arrays of `run_folder.REFINED_KEYS`, {"fit_before", "fit_after" (the rig's fit error
       x1e4 in the cube), "fit_before_capture", "fit_after_capture" (the capture's units,
       squared), "seconds" (the wall time, compilation included)}).

    Raises:
      ValueError: keypoints and points of different frame counts, too few frames.
    """
    from nmjax import metrics, skeleton_refine

    settings = RefineSettings() if settings is None else settings
    keypoints, points = np.asarray(keypoints, np.float32), np.asarray(points, np.float32)
    if keypoints.ndim != 3 or points.ndim != 3 or len(keypoints) != len(points):
        raise ValueError(
            f"{name}: keypoints (T, K, 4) and points (T, N, 3) of the same frames expected, got "
            f"{keypoints.shape} and {points.shape}"
        )
    tic = time.perf_counter()
    rig = unrefined_rig(name, keypoints, skeleton, 1.0)
    surface = points[0, point_subset(points.shape[1], settings.surface_points, settings.seed)]
    weights = kept_skin_weights(surface, keypoints[0], *skeleton)
    start = skeleton_refine.initial_params(
        rig.positions, rig.rotations, rig.rest_positions, rig.parents, weights
    )
    params, history = skeleton_refine.fit(
        start, surface, points, rig.parents, settings, progress=progress, desc=f"refine {name}"
    )
    refined = skeleton_refine.refined_arrays(params, rig.parents)
    frames = points[:, point_subset(points.shape[1], FIT_POINTS)]
    before = metrics.rig_fit_error(
        skeleton_refine.skin(
            rig.positions, rig.rotations, rig.rest_positions, weights.astype(np.float32), surface
        ),
        frames,
        box_scale,
    )
    after = metrics.rig_fit_error(
        skeleton_refine.skin(
            refined["positions"],
            refined["rotations"],
            refined["rest_positions"],
            refined["weights"],
            surface,
        ),
        frames,
        box_scale,
    )
    arrays = {
        **refined,
        "joints": rig.joints,
        "parents": rig.parents,
        "surface": surface,
        "box_scale": np.float64(box_scale),
        "chamfer_history": history["chamfer"],
        "settings": json.dumps(dataclasses.asdict(settings)),
    }
    errors = {
        "fit_before": before["cd"],
        "fit_after": after["cd"],
        "fit_before_capture": before["cd_capture"],
        "fit_after_capture": after["cd_capture"],
        "seconds": time.perf_counter() - tic,
    }
    return arrays, errors


def sequence_frames(
    run: Path, split: str, names: list[str]
) -> Iterator[tuple[str, np.ndarray, np.ndarray, float]]:
    """(name, keypoints (T, K, 4), points (T, N, 3), box scale) of the sequences `names` of a
    phase-1 run's split: the exported keypoints and the dataset's points of the same frames in
    the same cube (`trained.sequence_points`).

    Raises:
      FileNotFoundError: the dataset cannot be read here (names the command that prepares it).
      ValueError: keypoints exported from another number of frames.
    """
    from nmjax import run_folder
    from nmjax.config import SkelTrainConfig
    from nmjax.data.datasets import load_sequences
    from nmjax.data.normalize import normalization_box
    from nmjax.train import trained

    data = run_folder.load_config(run, SkelTrainConfig).data
    trajectories = run_folder.load_trajectories(run, split)
    sequences = {s.name: s for s in load_sequences(data.name, split, data.root)}
    for name in names:
        if name not in sequences:
            raise ValueError(
                f"{run_folder.keypoints_file(run, split)} holds {name!r}, which the dataset's "
                f"{split} split lacks; re-export with `nmjax export-keypoints --run {run}`"
            )
        seq = sequences[name]
        points, _ = trained.sequence_points(seq, data.sample_rate)
        keypoints = trajectories[name]
        if len(points) != len(keypoints):
            raise ValueError(
                f"{run_folder.keypoints_file(run, split)}[{name!r}] has {len(keypoints)} frames, "
                f"the dataset's sequence {len(points)}; re-export with `nmjax export-keypoints "
                f"--run {run}`"
            )
        _, scale = normalization_box(np.asarray(seq.vertices[:: data.sample_rate], np.float32))
        yield name, keypoints, points, float(np.asarray(scale).reshape(-1)[0])


def refine_run(
    run: str | Path,
    *,
    seq: str | None = None,
    split: str = "test",
    settings: RefineSettings | None = None,
    progress: bool = True,
    report: Callable[[RefinedSequence], None] | None = None,
) -> list[RefinedSequence]:
    """Refines the skeleton of every sequence of `split` of the phase-1 run `run` (or only
    `seq`) and writes each to `run_folder.refined_file(run, split, seq)`, replacing an earlier
    refinement of it.

    Args:
      run: a phase-1 run folder with skeleton.json and keypoints_<split>.npz, whose dataset can be
        read here.
      seq: one sequence of the split; None: all of them.
      split: "train" or "test".
      settings: the refinement's settings (default `RefineSettings()`).
      progress: a bar over every sequence's iterations.
      report: called with each sequence's `RefinedSequence` as soon as it is written.

    Returns:
      one `RefinedSequence` per sequence, in name order.

    Raises:
      FileNotFoundError, ValueError: one line naming the bad input and the fix.
    """
    from nmjax import run_folder

    run = Path(run)
    settings = RefineSettings() if settings is None else settings
    if split not in run_folder.SPLITS:
        raise ValueError(f"--split must be one of {', '.join(run_folder.SPLITS)}, got {split!r}")
    if not run.is_dir():
        raise FileNotFoundError(f"--run {run} does not exist; give a phase-1 run folder")
    if run_folder.run_kind(run) != "skel":
        raise ValueError(
            f"--run {run} is a phase-2 run; refine its phase-1 run (config.json's skel_run)"
        )
    skeleton = run_folder.pruned_skeleton(run)
    if skeleton is None:
        raise FileNotFoundError(
            f"{run / run_folder.SKELETON_FILE} not found; extract the skeleton first with "
            f"`nmjax extract-skeleton --run {run}`"
        )
    names = sorted(run_folder.load_trajectories(run, split))
    if seq is not None:
        if seq not in names:
            shown = ", ".join(names[:8]) + (
                f", ... ({len(names)} in all)" if len(names) > 8 else ""
            )
            raise ValueError(
                f"--seq {seq!r} is not a {split} sequence of {run}; available: {shown}"
            )
        names = [seq]
    done = []
    for name, keypoints, points, scale in sequence_frames(run, split, names):
        arrays, errors = refine_sequence(
            keypoints, points, skeleton, scale, settings, progress=progress, name=name
        )
        path = run_folder.write_refined(run, split, name, arrays)
        result = RefinedSequence(
            name=name,
            path=path,
            frames=len(points),
            joints=len(arrays["joints"]),
            points=len(arrays["surface"]),
            fit_before=errors["fit_before"],
            fit_after=errors["fit_after"],
            seconds=errors["seconds"],
        )
        done.append(result)
        if report is not None:
            report(result)
    return done
