"""Trained models out of run folders: the phase-1 detector (`Detector`) and its inference over
whole sequences and clips, skeleton extraction (`extract_run_skeleton`), the keypoint export
(`export_keypoints`), the phase-2 model (`restore_dynamics`).

What a run folder holds, its file names and the readers and writers of each file are
`nmjax.run_folder`'s (contract C10).

Phase 2 reads its keypoints in one of two ways (`DynTrainConfig.inputs`): "crop", the release's,
runs the phase-1 detector on every clip normalised with its own bounding box (`clip_voxels`,
`detect_clips`, `crop_inputs`); "sequence" reads the whole-sequence export keypoints_*.npz, a
cache that needs no detector (`load_trajectories`).

Nothing here runs a model or writes a file as a side effect of reading: a missing export is an
error naming the command that makes it.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import sys
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from nmjax import run_folder
from nmjax.config import DynTrainConfig, SkelTrainConfig, resolve_epochs
from nmjax.data.datasets import pad_with_last
from nmjax.models.detector import KeypointDetector
from nmjax.models.dynamics import Dynamics
from nmjax.run_folder import (
    CONFIG_FILE,
    FIGURES_DIR,
    SPLITS,
    checkpoint_steps,
    find_skel_run,
    keypoints_file,
    load_config,
    load_trajectories,
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
from nmjax.train import dyn, parallel, skel

# The run folder's names that the application modules (evaluate, view, tasks, export, release)
# read from here; `nmjax.run_folder` owns them.
AFFINITY_FILE = run_folder.AFFINITY_FILE
SKELETON_FILE = run_folder.SKELETON_FILE
STATS_FILE = run_folder.STATS_FILE
motion_format = run_folder.motion_format
pruned_skeleton = run_folder.pruned_skeleton
read_trajectories = run_folder.read_trajectories
run_kind = run_folder.run_kind
skeleton_intensities = run_folder.skeleton_intensities

CLIP_CHUNK = 8  # detector batches voxelised at once by `detect_clips` (bounds host memory)


# --- phase 1: the detector --------------------------------------------------------------------


def load_detector(run: str | Path, step: int | None = None) -> tuple[KeypointDetector, Any]:
    """The trained detector of a phase-1 run: (model, cfg).

    Restores `step`, else the best checkpoint by validation loss, else the latest.
    """
    return skel.restore_detector(run, step)


@dataclasses.dataclass
class Detector:
    """A restored phase-1 detector with compiled detect / reconstruct / decode functions.

    The functions are module-level jits keyed by the (static) graphdef, so every Detector of one
    configuration shares their compilations.
    """

    run: Path
    cfg: SkelTrainConfig
    graphdef: Any
    state: Any

    @classmethod
    def load(cls, run: str | Path, step: int | None = None) -> Detector:
        """The detector of checkpoint `step` (default: the best, see `load_detector`)."""
        model, cfg = load_detector(run, step)
        return cls.of(model, cfg, run)

    @classmethod
    def of(cls, model: KeypointDetector, cfg: SkelTrainConfig, run: str | Path) -> Detector:
        graphdef, state = nnx.split(model)
        # A trained state may be replicated over several hosts; inference here is local.
        return cls(Path(run), cfg, graphdef, parallel.to_local(state))

    def _batches(self, voxels: np.ndarray, fn) -> list[Any]:
        """`fn(graphdef, state, batch)` on `voxels` in batches of the training batch size, the
        last padded with the last crop, so one compiled shape serves every call."""
        b = self.cfg.data.batch_size
        padded = pad_with_last(voxels, -(-len(voxels) // b) * b)
        return [
            jax.device_get(fn(self.graphdef, self.state, jnp.asarray(padded[i : i + b])))
            for i in range(0, len(padded), b)
        ]

    def run_batches(self, voxels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Keypoints (C, T, K, 4) and reconstructions (C, T, G, G, G) of crops (C, T, G, G, G)."""
        outs = self._batches(voxels, _forward)
        n = len(voxels)
        return (
            np.concatenate([kp for kp, _ in outs])[:n],
            np.concatenate([recon for _, recon in outs])[:n],
        )

    def keypoints(self, voxels: np.ndarray) -> np.ndarray:
        """Keypoints (C, T, K, 4) of crops (C, T, G, G, G), without the reconstruction."""
        return np.concatenate(self._batches(voxels, detect_batch))[: len(voxels)]

    def decode(self, keypoints: np.ndarray, first_voxels: np.ndarray) -> np.ndarray:
        """Eq. 7 for given keypoints: (B, F, K, 4), first frame (B, G, G, G) -> (B, F, G, G, G)."""
        return np.asarray(
            _decode(self.graphdef, self.state, jnp.asarray(keypoints), jnp.asarray(first_voxels))
        )


@functools.partial(jax.jit, static_argnames="graphdef")
def _forward(graphdef, state, voxels):
    out = nnx.merge(graphdef, state)(voxels)
    return out["keypoints"], out["recon"]


@functools.partial(jax.jit, static_argnames="graphdef")
def detect_batch(graphdef, state, voxels):
    """Keypoints (B, T, K, 4) of crops (B, T, G, G, G): the detector's forward without the
    decoder, compiled once per shape (what `Detector.keypoints` and `nmjax bench --phase detect`
    run)."""
    return nnx.merge(graphdef, state).detect(voxels)[1]


@functools.partial(jax.jit, static_argnames="graphdef")
def _decode(graphdef, state, keypoints, first_voxels):
    model = nnx.merge(graphdef, state)
    features = model.features(first_voxels)  # c_1 of frame ts: f_feat sees one frame
    return model.decode(keypoints, features, first_voxels)


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
    keypoints_{train,test}.npz of the run's final detector (its latest checkpoint).

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
        detector = Detector.load(run, checkpoint_steps(run)[-1])
        if parallel.is_primary():
            for split in SPLITS:
                export_keypoints(run, split, detector=detector)


# --- phase 1 -> phase 2: keypoints of clips, each normalised on its own ("crop" inputs) ----------


def crop_starts(num_frames: int, frames: int, sample_rate: int) -> np.ndarray:
    """Every first frame of a crop of `frames` frames taken every `sample_rate` frames: the starts
    the release's random crop draws from (0 alone for a shorter sequence, padded when cut)."""
    from nmjax.data.datasets import crop_span

    return np.arange(max(num_frames - crop_span(frames, sample_rate), 0) + 1)


def clip_voxels(
    seq, start: int, frames: int, data: Any, box_frames: int | None = None
) -> np.ndarray:
    """(frames, G, G, G): a clip of `seq` normalised on its own bounding box and voxelised.

    Frames start, start + r, ... (r = `data.sample_rate`, padded with the last frame past the
    end), mapped into [-1, 1)^3 with the box of the clip's first `box_frames` frames (default: all
    of them, as a training crop; DESIGN section 4) and voxelised on `data.grid`. A smaller box
    keeps a longer clip in the frame of its first crop; points that leave the box land in the
    border cells.

    Args:
      seq: a `nmjax.data.datasets.Sequence`.
      start: first frame, in frames of the original sequence.
      frames: frames of the clip.
      data: the phase-1 run's `DataConfig` (grid, sample rate).
      box_frames: how many leading frames the bounding box spans.
    """
    from nmjax.data.datasets import crop_sequence
    from nmjax.data.normalize import normalize_sequence
    from nmjax.data.voxelize import voxelize

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
    over all of them (as `dyn.validation_crops` picks windows of whole sequences)."""
    from nmjax.data.datasets import crop_span

    span = crop_span(frames, sample_rate)
    clips = [
        (seq, int(t))
        for seq in seqs
        for t in crop_starts(seq.num_frames, frames, sample_rate)
        if t % span == 0
    ]
    if len(clips) > dyn.MAX_VAL_CROPS:
        keep = np.linspace(0, len(clips) - 1, dyn.MAX_VAL_CROPS).astype(int)
        clips = [clips[i] for i in keep]
    return clips


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


def crop_inputs(
    detector: Detector, train: list[Any], test: list[Any], frames: int
) -> dyn.Phase2Inputs:
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
    val_cond = detect_clips(detector, val, frames, detect=dyn.condition_frames(frames))
    return dyn.Phase2Inputs(DetectedCrops(detector, clips, frames), val_x, val_cond)


def split_sequences(detector: Detector, split: str) -> dict[str, Any]:
    """{name: Sequence} of a split of the detector's dataset (its phase-1 run's data and root)."""
    from nmjax.data.datasets import load_sequences

    data = detector.cfg.data
    return {seq.name: seq for seq in load_sequences(data.name, split, data.root)}


def phase2_detector(skel_run: str | Path) -> Detector:
    """The detector phase 2 runs on crops ("crop" inputs): the phase-1 run's best checkpoint, else
    its latest (`Detector.load`, as `nmjax export-keypoints` and the tasks).

    Raises:
      FileNotFoundError: the folder holds no detector checkpoint (names both ways out).
    """
    skel_run = Path(skel_run)
    has_config = (skel_run / CONFIG_FILE).is_file()
    if not has_config or not checkpoint_steps(skel_run):
        raise FileNotFoundError(
            f"{skel_run} holds no phase-1 detector checkpoint, and phase-2 inputs 'crop' run the "
            "detector on every crop; give a trained phase-1 run (--skel-run) or train on its "
            "exported keypoints with --set inputs=sequence"
        )
    return Detector.load(skel_run)


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


def train_dynamics(
    cfg: DynTrainConfig, *, resume: bool = False, progress: bool = True, **kwargs: Any
) -> tuple[Path, list[dict[str, float]]]:
    """Phase 2 on the phase-1 run `cfg.skel_run` (default: the latest of `cfg.data`), then
    `dyn.train`. The resolved phase-1 folder is stored in the run's config.json.

    Reads the run's skeleton and, by `cfg.inputs`, its detector and dataset ("crop": the
    detector runs on each crop when a batch first draws it, `crop_inputs`) or its exported
    keypoints ("sequence"). Everything that can be refused is checked before the run folder is
    made.
    """
    dyn.check_config(cfg)
    skel_run = find_skel_run(cfg.data, cfg.skel_run)
    skeleton = read_skeleton(skel_run)
    cfg = dataclasses.replace(cfg, skel_run=str(skel_run))
    if cfg.inputs == "sequence":
        trajectories = {split: load_trajectories(skel_run, split) for split in SPLITS}
        for split, traj in trajectories.items():
            k = {x.shape[1] for x in traj.values()}
            if k != {skeleton.num_keypoints}:
                raise ValueError(
                    f"{keypoints_file(skel_run, split)} has K={sorted(k)} keypoints but "
                    f"skeleton.json has {skeleton.num_keypoints} joints; re-export the keypoints "
                    f"with `nmjax export-keypoints --run {skel_run}`"
                )

        def inputs() -> dyn.Phase2Inputs:
            return dyn.sequence_inputs(trajectories, cfg.frames)

    else:
        detector = phase2_detector(skel_run)
        if detector.cfg.model.num_keypoints != skeleton.num_keypoints:
            raise ValueError(
                f"the detector of {skel_run} has K={detector.cfg.model.num_keypoints} keypoints "
                f"but skeleton.json has {skeleton.num_keypoints} joints; extract the skeleton "
                f"again with `nmjax extract-skeleton --run {skel_run}`"
            )
        seqs = {split: list(split_sequences(detector, split).values()) for split in SPLITS}

        def inputs() -> dyn.Phase2Inputs:
            return crop_inputs(detector, seqs["train"], seqs["test"], cfg.frames)

    train_count = len(trajectories["train"]) if cfg.inputs == "sequence" else len(seqs["train"])
    cfg = resolve_epochs(cfg, train_count, cfg.batch_size)
    return dyn.train(
        cfg,
        (skeleton.parents, skeleton.order),
        inputs,
        resume=resume,
        progress=progress,
        **kwargs,
    )


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
