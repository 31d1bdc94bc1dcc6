"""What phase 2 is fed: the keypoint crops it trains on, its validation crops and the keypoints
its validation generation conditions on, by one of two routes (`DynTrainConfig.data.inputs`), both
a `Phase2Inputs`:

- "crop" (the release's): every T-frame training crop normalised with its own bounding box and
  run through the frozen phase-1 detector (`crop_inputs`, `DetectedCrops`). The keypoints of a
  crop depend on nothing but its start frame (the detector is frozen, phase 2 does not augment),
  so each crop is detected when a batch first draws it and kept: the inputs the release's step
  computes, at most one detector pass per start (never more than the crops drawn), and no wait
  before the first step.
- "sequence": crops cut from the whole-sequence trajectories of `keypoints_{train,test}.npz`
  (`sequence_inputs`, a `CropTable`), the named fast route that needs no detector.

Validation takes non-overlapping crops of the test split, at most `MAX_VAL_CROPS` spread over it
(`validation_crops`, `validation_clips`); generation conditions on their first
`condition_frames(T)` frames. Which starts each step draws is the step's business
(`dyn.CropDraws`); `phase2_inputs` reads a phase-1 run folder and refuses, before any run folder
is made, inputs that do not fit its skeleton.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import numpy as np

from nmjax import run_folder
from nmjax.config import DynTrainConfig
from nmjax.data.datasets import crop_sequence, crop_span, load_sequences, pad_with_last
from nmjax.data.normalize import normalize_sequence
from nmjax.data.voxelize import voxelize
from nmjax.train.trained import Detector

MAX_VAL_CROPS = 64
CLIP_CHUNK = 8  # detector batches voxelised at once by `detect_clips` (bounds host memory)


def condition_frames(frames: int) -> int:
    """T_cond used in validation generation: a quarter of the crop, at least one frame."""
    return max(1, frames // 4)


class TrainingCrops(Protocol):
    """What the step's batches are cut from: `CropTable` or `DetectedCrops`."""

    @property
    def num_starts(self) -> int: ...

    @property
    def num_keypoints(self) -> int: ...

    def batch(self, chosen: np.ndarray) -> np.ndarray: ...


class Phase2Inputs(NamedTuple):
    """What phase 2 trains and validates on, whichever `DynTrainConfig.data.inputs` made it.

    Attributes:
      crops: the training crops (`TrainingCrops`); each step draws B of its starts uniformly.
      val: (V, T, K, 4) validation crops.
      val_cond: (V, T_cond, K, 4) the keypoints the validation generation conditions on
        (T_cond = `condition_frames(T)`).
    """

    crops: TrainingCrops
    val: np.ndarray
    val_cond: np.ndarray


# --- "sequence": crops cut from whole-sequence trajectories -------------------------------------


def crop_table(trajectories: dict[str, np.ndarray], frames: int) -> tuple[np.ndarray, np.ndarray]:
    """All sequences concatenated along time, and every start frame of a crop of `frames`.

    Sequences shorter than `frames` are padded with their last frame (as in the phase-1 pipeline).

    Returns:
      poses (F, K, 4) float32 and starts (S,) int32; `poses[s:s + frames]` is a valid crop for
      every s in `starts`.
    """
    pieces, starts, offset = [], [], 0
    for name in sorted(trajectories):
        x = pad_with_last(trajectories[name], frames)
        pieces.append(x)
        starts.append(offset + np.arange(len(x) - frames + 1))
        offset += len(x)
    return np.concatenate(pieces).astype(np.float32), np.concatenate(starts).astype(np.int32)


class CropTable(NamedTuple):
    """Training crops cut from a table of poses (the "sequence" route, `crop_table`).

    Attributes:
      poses: (F, K, 4); starts: (S,) int32, `poses[s:s + frames]` is a crop for every s.
      frames: T.
    """

    poses: np.ndarray
    starts: np.ndarray
    frames: int

    @property
    def num_starts(self) -> int:
        return len(self.starts)

    @property
    def num_keypoints(self) -> int:
        return int(self.poses.shape[1])

    def batch(self, chosen: np.ndarray) -> np.ndarray:
        """(B, T, K, 4): the crops of the starts at indices `chosen` (B,)."""
        return self.poses[self.starts[chosen][:, None] + np.arange(self.frames)]


def spread(items: list[Any]) -> list[Any]:
    """At most `MAX_VAL_CROPS` of `items`, evenly spaced over all of them (first and last kept)."""
    if len(items) <= MAX_VAL_CROPS:
        return items
    return [items[i] for i in np.linspace(0, len(items) - 1, MAX_VAL_CROPS).astype(int)]


def validation_crops(trajectories: dict[str, np.ndarray], frames: int) -> np.ndarray:
    """Deterministic validation crops (V, T, K, 4): non-overlapping windows, at most 64."""
    poses, starts = crop_table(trajectories, frames)
    starts = np.asarray(spread(list(starts[:: max(frames, 1)])), np.int32)
    return poses[starts[:, None] + np.arange(frames)]


def sequence_inputs(trajectories: dict[str, dict[str, np.ndarray]], frames: int) -> Phase2Inputs:
    """The "sequence" route: crops cut from whole-sequence trajectories.

    Args:
      trajectories: {"train": ..., "test": ...}, each {sequence: (T_seq, K, 4)} as in
        keypoints_<split>.npz.
      frames: T.

    Returns:
      every start of `crop_table` on the training split; `validation_crops` of the test split,
      conditioned on their own first T_cond frames.
    """
    poses, starts = crop_table(trajectories["train"], frames)
    val = validation_crops(trajectories["test"], frames)
    return Phase2Inputs(CropTable(poses, starts, frames), val, val[:, : condition_frames(frames)])


# --- "crop": the frozen detector on every crop, each normalised on its own ----------------------


def crop_starts(num_frames: int, frames: int, sample_rate: int) -> np.ndarray:
    """Every first frame of a crop of `frames` frames taken every `sample_rate` frames: the starts
    the release's random crop draws from (0 alone for a shorter sequence, padded when cut)."""
    return np.arange(max(num_frames - crop_span(frames, sample_rate), 0) + 1)


def clip_voxels(
    seq, start: int, frames: int, data: Any, box_frames: int | None = None
) -> np.ndarray:
    """(frames, G, G, G): a clip of `seq` normalised on its own bounding box and voxelised.

    Frames start, start + r, ... (r = `data.sample_rate`, padded with the last frame past the
    end), mapped into [-1, 1)^3 with the box of the clip's first `box_frames` frames (default: all
    of them, as a training crop; docs/architecture.md §4) and voxelised on `data.grid`. A smaller
    box keeps a longer clip in the frame of its first crop; points that leave the box land in the
    border cells.

    Args:
      seq: a `nmjax.data.datasets.Sequence`.
      start: first frame, in frames of the original sequence.
      frames: frames of the clip.
      data: the phase-1 run's `DataConfig` (grid, sample rate).
      box_frames: how many leading frames the bounding box spans.
    """
    points, _ = crop_sequence(seq, frames, data.sample_rate, start)
    points, _ = normalize_sequence(points, box_frames=box_frames)
    return voxelize(points, data.grid)


def detect_clips(
    detector: Detector,
    clips: list[tuple[Any, int]],
    frames: int,
    detect: int | None = None,
    *,
    desc: str | None = None,
) -> np.ndarray:
    """Keypoints of clips each normalised on its own: (C, detect, K, 4).

    Every clip (sequence, start) of `frames` frames is normalised with its own bounding box and
    voxelised (`clip_voxels`); its first `detect` frames (default all) go through the detector
    together, so the detector's temporal mean (Eq. 6) is the mean over exactly those frames.

    Args:
      detector: the phase-1 detector.
      clips: [(Sequence, start frame)].
      frames: frames of each clip (its bounding box spans all of them).
      detect: leading frames run through the detector.
      desc: a tqdm bar with this label over the clips; None: no bar.
    """
    from tqdm import tqdm

    detect = frames if detect is None else detect
    chunk = detector.cfg.data.batch_size * CLIP_CHUNK
    out = []
    with tqdm(total=len(clips), desc=desc, unit="clip", disable=desc is None) as bar:
        for i in range(0, len(clips), chunk):
            part = clips[i : i + chunk]
            voxels = np.stack(
                [clip_voxels(seq, start, frames, detector.cfg.data)[:detect] for seq, start in part]
            )
            out.append(detector.keypoints(voxels))
            bar.update(len(part))
    if not out:
        return np.zeros((0, detect, detector.cfg.model.num_keypoints, 4), np.float32)
    return np.concatenate(out).astype(np.float32)


def validation_clips(seqs: list[Any], frames: int, sample_rate: int) -> list[tuple[Any, int]]:
    """Deterministic validation clips: non-overlapping crops of every sequence, at most 64 spread
    over all of them (as `validation_crops` picks windows of whole sequences)."""
    span = crop_span(frames, sample_rate)
    return spread(
        [
            (seq, int(t))
            for seq in seqs
            for t in crop_starts(seq.num_frames, frames, sample_rate)
            if t % span == 0
        ]
    )


class DetectedCrops:
    """The "crop" route's training crops: the detector on each crop (`detect_clips`, normalised
    on its own box), run when a batch first draws the crop and kept for every later draw.

    Detector frame passes: at most min(starts, crops drawn) x frames, and none before the first
    step. A crop's keypoints depend on nothing but its (sequence, start), so a resumed run, which
    starts with none kept, recomputes the same ones.

    Args:
      detector: the phase-1 run's detector.
      clips: [(Sequence, start frame)] every training crop the steps draw from.
      frames: T of phase 2.
    """

    def __init__(self, detector: Detector, clips: list[tuple[Any, int]], frames: int):
        self.detector, self.clips, self.frames = detector, clips, frames
        self._kept: dict[int, np.ndarray] = {}

    @property
    def num_starts(self) -> int:
        return len(self.clips)

    @property
    def num_keypoints(self) -> int:
        return self.detector.cfg.model.num_keypoints

    @property
    def detected(self) -> int:
        """Crops detected so far (each once): the detector ran on `detected x frames` frames."""
        return len(self._kept)

    def batch(self, chosen: np.ndarray) -> np.ndarray:
        """(B, T, K, 4): the crops at indices `chosen` (B,), detecting the new ones together."""
        chosen = [int(i) for i in chosen]
        new = sorted(set(chosen) - self._kept.keys())
        if new:
            found = detect_clips(self.detector, [self.clips[i] for i in new], self.frames)
            self._kept.update(zip(new, found, strict=True))
        return np.stack([self._kept[i] for i in chosen])

    def postfix(self) -> dict[str, str]:
        """For the progress bar: crops detected so far of the starts."""
        return {"crops_detected": f"{self.detected}/{self.num_starts}"}


def crop_inputs(detector: Detector, train: list[Any], test: list[Any], frames: int) -> Phase2Inputs:
    """The "crop" phase-2 inputs: the detector on each crop, each normalised on its own.

    Training: a crop of `frames` frames at every start of every training sequence
    (`crop_starts`), the crops the release's random crop draws from; the steps draw them
    uniformly and each is detected when first drawn (`DetectedCrops`). Validation: the
    `validation_clips` of the test sequences (at most 64), detected now, and for their generation
    the first T_cond frames of each clip detected on their own (`Dynamics.generate`'s
    conditioning, as in the release).

    Args:
      detector: the phase-1 run's detector.
      train, test: the `Sequence`s of the two splits.
      frames: T of phase 2.
    """
    rate = detector.cfg.data.sample_rate
    clips = [(seq, int(t)) for seq in train for t in crop_starts(seq.num_frames, frames, rate)]
    val = validation_clips(test, frames, rate)
    val_x = detect_clips(detector, val, frames)
    val_cond = detect_clips(detector, val, frames, detect=condition_frames(frames))
    return Phase2Inputs(DetectedCrops(detector, clips, frames), val_x, val_cond)


def split_sequences(detector: Detector, split: str) -> dict[str, Any]:
    """{name: Sequence} of a split of the detector's dataset (the name and root of its config:
    its phase-1 run's, or the root `Detector.reading` gave it)."""
    data = detector.cfg.data
    return {seq.name: seq for seq in load_sequences(data.name, split, data.root)}


def phase2_detector(skel_run: str | Path, root: str | None = None) -> Detector:
    """The detector phase 2 runs on crops ("crop" inputs): the phase-1 run's detector as every
    reader of the run takes it (`Detector.load`: the best checkpoint by validation loss), reading
    the sequences from `root` (the phase-2 run's `data.root`; None: the phase-1 run's).

    Raises:
      FileNotFoundError: the folder holds no detector checkpoint (names both ways out).
    """
    skel_run = Path(skel_run)
    has_config = (skel_run / run_folder.CONFIG_FILE).is_file()
    if not has_config or not run_folder.checkpoint_steps(skel_run):
        raise FileNotFoundError(
            f"{skel_run} holds no phase-1 detector checkpoint, and phase-2 inputs 'crop' run the "
            "detector on every crop; give a trained phase-1 run (--skel-run) or train on its "
            "exported keypoints with --set data.inputs=sequence"
        )
    return Detector.load(skel_run).reading(root)


# --- from a phase-1 run folder -----------------------------------------------------------------


def phase2_inputs(
    cfg: DynTrainConfig, skel_run: Path, num_keypoints: int
) -> tuple[int, Callable[[], Phase2Inputs]]:
    """The inputs of `cfg.data.inputs` from the phase-1 run `skel_run`, checked but not yet
    built.

    "sequence" reads the run's exported keypoints now; "crop" restores its detector and lists
    its dataset's sequences now, and detects the validation clips only when the maker is called
    (the training crops later still, as batches draw them).

    Args:
      cfg: the phase-2 configuration (its `data.inputs`, T = `data.frames` and `data.root`).
      skel_run: the phase-1 run folder.
      num_keypoints: K of the run's skeleton; inputs of another K are refused.

    Returns:
      (number of training sequences, what the epochs count; a maker of the `Phase2Inputs`,
      called once the phase-2 run folder is accepted, so a refused run costs nothing).

    Raises:
      FileNotFoundError, ValueError: a missing export or detector, or K that differs from the
        skeleton's (naming the command that makes them agree).
    """
    frames = cfg.data.frames
    if cfg.data.inputs == "sequence":
        trajectories = {
            split: run_folder.load_trajectories(skel_run, split) for split in run_folder.SPLITS
        }
        for split, traj in trajectories.items():
            k = {x.shape[1] for x in traj.values()}
            if k != {num_keypoints}:
                raise ValueError(
                    f"{run_folder.keypoints_file(skel_run, split)} has K={sorted(k)} keypoints "
                    f"but skeleton.json has {num_keypoints} joints; re-export the keypoints "
                    f"with `nmjax export-keypoints --run {skel_run}`"
                )
        return len(trajectories["train"]), lambda: sequence_inputs(trajectories, frames)
    detector = phase2_detector(skel_run, cfg.data.root)
    if detector.cfg.model.num_keypoints != num_keypoints:
        raise ValueError(
            f"the detector of {skel_run} has K={detector.cfg.model.num_keypoints} keypoints "
            f"but skeleton.json has {num_keypoints} joints; extract the skeleton "
            f"again with `nmjax extract-skeleton --run {skel_run}`"
        )
    seqs = {split: list(split_sequences(detector, split).values()) for split in run_folder.SPLITS}
    return len(seqs["train"]), lambda: crop_inputs(detector, seqs["train"], seqs["test"], frames)
