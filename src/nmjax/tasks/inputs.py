"""What the task commands run on (`nmjax generate`, `interpolate`, `retarget`).

Inputs are test sequences of the phase-1 run, as the phase-2 run was fed (its `inputs`): "crop"
runs the phase-1 detector on each clip normalised with its own bounding box, as the release's
generation and interpolation demos do; "sequence" cuts the clips from the whole-sequence
keypoints_test.npz (`run_retarget` always does). With `--source-file` the one input is a
point-sequence file instead, detected as the release's demos take it. Each command writes into
`out` (default `RUN/<command>`) the keypoints as .npz (`nmjax.tasks.outputs`), a GIF of the motion
and a PNG strip of frames.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from nmjax.data.datasets import pad_with_last
from nmjax.train import trained


def pick_inputs(
    trajectories: dict[str, np.ndarray],
    count: int,
    frames: int | None,
    names: list[str] | None = None,
) -> tuple[list[str], np.ndarray]:
    """The first `count` sequences (sorted names, or `names`), frames 0..frames-1 of each
    (`frames` None: every frame of the longest of them).

    Sequences shorter than `frames` are padded with their last frame. Returns (names, (I, F, K, 4)).
    """
    chosen = sorted(trajectories) if names is None else names
    missing = [n for n in chosen if n not in trajectories]
    if missing:
        raise ValueError(f"no test sequence named {missing}; available: {sorted(trajectories)}")
    chosen = chosen[:count]
    if frames is None:
        frames = max(len(trajectories[name]) for name in chosen)
    crops = [pad_with_last(trajectories[name][:frames], frames) for name in chosen]
    return chosen, np.stack(crops).astype(np.float32)


@dataclasses.dataclass
class TaskClips:
    """Observed test clips of a task command, in the coordinates the model is conditioned in.

    Attributes:
      names: the sequences, one clip each (from frame 0).
      keypoints: (I, F, K, 4) the clips' keypoints.
      real_frames: (I,) frames of each clip the sequence really has (the rest repeats its last).
      first_voxels: (I, G, G, G) each clip's first voxel frame, when asked for (decoding).
    """

    names: list[str]
    keypoints: np.ndarray
    real_frames: np.ndarray
    first_voxels: np.ndarray | None = None


# --- a motion from a point-sequence file (`--source-file`) -----------------------------------


def point_file_keypoints(
    detector: trained.Detector, path: str | os.PathLike, frames: int | None, sample_rate: int
) -> tuple[np.ndarray, np.ndarray]:
    """A point-sequence file's motion as the release's demos take it: `frames` frames from the
    first, every `sample_rate`-th, normalised with one bounding box over them (docs/architecture.md
    §4, the release's episodic normalisation), voxelised, and run through the detector as one crop
    (its spatio-temporal branch sees their mean).

    Args:
      detector: the phase-1 detector.
      path: a (T, N, >= 3) .npy (`nmjax.data.meshes.load_point_sequence`).
      frames: F, the crop length; None: every `sample_rate`-th frame of the file.
      sample_rate: the frame step.

    Returns:
      keypoints (F, K, 4) and voxels (F, G, G, G).

    Raises:
      ValueError: the file has fewer than (F - 1) sample_rate + 1 frames.
    """
    from nmjax.data.meshes import load_point_sequence
    from nmjax.data.normalize import normalize_sequence
    from nmjax.data.voxelize import voxelize

    points = load_point_sequence(path)
    if frames is None:
        frames = (len(points) - 1) // sample_rate + 1
    span = (frames - 1) * sample_rate + 1
    if len(points) < span:
        raise ValueError(
            f"{path} has {len(points)} frames; {frames} frames every {sample_rate} need {span} "
            "(ask for fewer frames or a smaller --source-rate)"
        )
    clip, _ = normalize_sequence(points[:span:sample_rate])
    voxels = voxelize(clip, detector.cfg.data.grid)
    # One crop: a batch of one instead of the training batch the detector pads to.
    return detector.with_batch_size(1).keypoints(voxels[None])[0], voxels


def source_file_clip(
    skel_run: Path, path: str | os.PathLike, frames: int | None, sample_rate: int | None
) -> tuple[str, np.ndarray, np.ndarray]:
    """(name, keypoints (1, F, K, 4), first voxel frame (1, G, G, G)) of `point_file_keypoints`
    with the phase-1 run's detector; `sample_rate` None takes the run's, `frames` None every
    frame at that rate."""
    detector = trained.Detector.load(skel_run)
    rate = detector.cfg.data.sample_rate if sample_rate is None else sample_rate
    keypoints, voxels = point_file_keypoints(detector, path, frames, rate)
    return Path(path).stem, keypoints[None].astype(np.float32), voxels[None, 0]
