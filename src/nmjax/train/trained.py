"""A trained model in a run folder, for everything after training: one owner below both trainers.

- Phase 1: the detector restored for inference (`restore_detector`, `Detector`, with its
  compiled detect / reconstruct / decode functions and an inference batch of its own), its
  keypoints over whole sequences (`export_keypoints`), the skeleton of the run's affinity
  (`extract_run_skeleton`) and the artefacts that complete a phase-1 run (`complete_phase1`,
  which `skel.train_skeleton` calls as its last stage).
- Phase 2: the dynamics model restored for inference (`restore_dynamics`, `load_phase2`) and the
  runs a comparison pairs (`find_vrnn_run`, `phase2_runs`).

Inference restores a checkpoint's "model" part alone (and the weight average, when the run
keeps one): no optimizer state is built, except for a checkpoint of the earlier layout that holds
the whole training state in one item (`checkpoints.Checkpointer.restore_parts`).

What a run folder holds, its file names and the readers and writers of each file are
`nmjax.run_folder`'s (contract C10). Nothing here runs a model or writes a file as a side effect
of reading: a missing export is an error naming the command that makes it.
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
from nmjax.config import DynTrainConfig, SkelTrainConfig
from nmjax.data.datasets import pad_with_last
from nmjax.models.detector import KeypointDetector
from nmjax.models.dynamics import Dynamics
from nmjax.skeleton import DEFAULT_NEIGHBORS, PRUNE_THRESHOLD, Skeleton, extract_skeleton, prune
from nmjax.train import checkpoints, optim, parallel

# The validation scalar phase 1 ranks its checkpoints by: the best is the trained detector.
BEST_METRIC = "val/loss"


# --- phase 1: the detector --------------------------------------------------------------------


def build_detector(cfg: SkelTrainConfig, seed: int | None = None) -> KeypointDetector:
    """The detector of `cfg`, initialised from `seed` (default `cfg.seed`)."""
    return KeypointDetector(cfg.model, rngs=nnx.Rngs(cfg.seed if seed is None else seed))


def inference_parts(model: nnx.Module, optimizer: optim.OptimizerSettings) -> dict[str, Any]:
    """The abstract checkpoint parts the trained model of `model`'s run is restored from:
    {"model"[, "ema" (the weight average) when the run keeps one]} (`optim.trained_model`)."""
    parts = {"model": checkpoints.abstract_state(nnx.state(model))}
    if optimizer.ema_decay > 0:
        params = nnx.state(model, nnx.Param)
        parts["ema"] = jax.eval_shape(lambda: optimizer.make_ema().init(params))
    return parts


def restore_trained(
    run: Path, model: nnx.Module, optimizer: optim.OptimizerSettings, ckpt, step: int
) -> nnx.Module:
    """The trained model of checkpoint `step` of `run` (`optim.trained_model`) in the structure
    of the freshly built `model`, restored without its optimizer state."""
    graphdef, _ = nnx.split(model)

    def whole_state() -> dict[str, Any]:  # a checkpoint of the earlier one-item layout
        params = nnx.state(model, nnx.Param)
        state = {
            "model": nnx.state(model),
            "opt": jax.eval_shape(lambda: optimizer.make().init(params)),
        }
        if optimizer.ema_decay > 0:
            state["ema"] = jax.eval_shape(lambda: optimizer.make_ema().init(params))
        return checkpoints.abstract_state(state)

    _, parts = ckpt.restore_parts(inference_parts(model, optimizer), step, whole_state)
    return optim.trained_model(graphdef, parts, optimizer.ema_decay)


def restore_detector(
    run: str | Path, step: int | None = None
) -> tuple[KeypointDetector, SkelTrainConfig]:
    """The trained detector of a phase-1 run and its configuration: checkpoint `step`, else the
    best by validation loss, else the latest (the weight average when the run keeps one).
    `Detector.load` wraps it for inference."""
    run = Path(run)
    cfg = run_folder.load_config(run, SkelTrainConfig)
    # Built concretely: the detector's initialisation does host-side work eval_shape cannot trace.
    model = build_detector(cfg)
    with checkpoints.Checkpointer.of_run(run, cfg.loop, BEST_METRIC) as ckpt:
        if step is None:
            best = ckpt.best_step()
            step = best if best is not None else ckpt.latest_step()
        if step is None:
            raise FileNotFoundError(f"{run} holds no checkpoint; train it first (train-skel)")
        trained = restore_trained(run, model, optim.OptimizerSettings.of(cfg), ckpt, step)
    return trained, cfg


@dataclasses.dataclass
class Detector:
    """A restored phase-1 detector with compiled detect / reconstruct / decode functions.

    The functions are module-level jits keyed by the (static) graphdef, so every Detector of one
    configuration shares their compilations. Crops are run `batch_size` at a time (the training
    batch unless asked otherwise), the last batch padded, so one compiled shape serves every call.
    """

    run: Path
    cfg: SkelTrainConfig
    graphdef: Any
    state: Any
    batch_size: int

    @classmethod
    def load(
        cls, run: str | Path, step: int | None = None, batch_size: int | None = None
    ) -> Detector:
        """The detector of checkpoint `step`, by default the run's best by validation loss
        (`restore_detector`): the one the release keeps, whose affinity and keypoint statistics
        the trainer writes and whose keypoints `complete_phase1` exports, so the skeleton, the
        exported keypoints and every later reader agree. `batch_size`: crops per compiled call
        (default: the run's training batch)."""
        model, cfg = restore_detector(run, step)
        return cls.of(model, cfg, run, batch_size)

    @classmethod
    def of(
        cls,
        model: KeypointDetector,
        cfg: SkelTrainConfig,
        run: str | Path,
        batch_size: int | None = None,
    ) -> Detector:
        graphdef, state = nnx.split(model)
        batch = cfg.data.batch_size if batch_size is None else batch_size
        if batch < 1:
            raise ValueError(f"a detector's inference batch must be >= 1, got {batch}")
        # A trained state may be replicated over several hosts; inference here is local.
        return cls(Path(run), cfg, graphdef, parallel.to_local(state), batch)

    def reading(self, root: str | None) -> Detector:
        """The same detector reading its dataset's sequences from `root` instead of the folder
        its run's config names (a phase-2 run's `data.root`); None: its run's."""
        if root is None:
            return self
        data = dataclasses.replace(self.cfg.data, root=root)
        return dataclasses.replace(self, cfg=dataclasses.replace(self.cfg, data=data))

    def with_batch_size(self, batch_size: int) -> Detector:
        """The same detector, run `batch_size` crops at a time."""
        if batch_size < 1:
            raise ValueError(f"a detector's inference batch must be >= 1, got {batch_size}")
        return dataclasses.replace(self, batch_size=batch_size)

    def _batches(self, voxels: np.ndarray, fn) -> list[Any]:
        """`fn(graphdef, state, batch)` on `voxels` in batches of `batch_size`, the last padded
        with the last crop."""
        b = self.batch_size
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


# --- phase 1: whole sequences -----------------------------------------------------------------


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
    (docs/architecture.md, "Conventions"), voxelised, cut into consecutive windows of T frames
    (the last padded by repeating the last frame) and run through the detector in compiled
    batches. `data_root` reads the sequences from another copy of the run's dataset (e.g. a set
    of longer synthetic sequences), `path` writes the file elsewhere.
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
    out = run_folder.keypoints_file(run, split) if path is None else path
    return run_folder.write_trajectories(out, arrays)


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
    affinity, stats = run_folder.read_skeleton_inputs(run)
    skeleton = extract_skeleton(affinity, n_neighbors, stats["intensities"], method=method)
    pruned, keep = prune(skeleton, stats["intensities"], prune_threshold)
    run_folder.write_skeleton(
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
        run / run_folder.FIGURES_DIR / "skeleton.png",
        skeleton,
        stats["example_keypoints"],
        stats["example_voxels"],
        keep,
        title=f"{run.name}: K={skeleton.num_keypoints}, kept {int(keep.sum())}",
    )
    return skeleton


def complete_phase1(run: str | Path, *, export: bool = True) -> None:
    """The artefacts phase 2 needs after training, once affinity.npy and keypoint_stats.npz are
    written: skeleton.json and (with `export`) keypoints_{train,test}.npz.

    Both come from the run's best checkpoint by validation loss: the skeleton from the affinity
    the trainer wrote of it, the keypoints from `Detector.load`'s detector, the one the release
    keeps and every later reader (tasks, evaluation, phase 2's "crop" inputs) restores. The last
    checkpoint may be a worse model that merely came later.

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
            for split in run_folder.SPLITS:
                export_keypoints(run, split, detector=detector)


# --- phase 2: the dynamics model --------------------------------------------------------------


def build_dynamics(
    cfg: DynTrainConfig, parents: tuple[int, ...], order: tuple[int, ...]
) -> Dynamics:
    """The dynamics model of `cfg` on the skeleton (`parents`, `order`), from `cfg.seed`."""
    return Dynamics(cfg.model, parents, order, rngs=nnx.Rngs(cfg.seed))


def restore_model(
    run: str | Path,
    cfg: DynTrainConfig,
    parents: tuple[int, ...],
    order: tuple[int, ...],
    step: int | None = None,
) -> Dynamics:
    """The model of checkpoint `step` (default: the latest) of the phase-2 run `run`, whose
    configuration is `cfg` and whose skeleton is (`parents`, `order`); phase 2 keeps no best
    checkpoint (its loop ranks none), so the latest is its trained model. `restore_dynamics`
    reads both from the folder."""
    model = nnx.eval_shape(lambda: build_dynamics(cfg, parents, order))
    with checkpoints.Checkpointer.of_run(run, cfg.loop) as ckpt:
        step = ckpt.latest_step() if step is None else step
        if step is None:
            raise FileNotFoundError(f"{run} holds no checkpoint; train it first (train-dyn)")
        return restore_trained(Path(run), model, optim.OptimizerSettings.of(cfg), ckpt, step)


def restore_dynamics(run: str | Path, step: int | None = None) -> Dynamics:
    """The trained dynamics model of a phase-2 run folder (latest checkpoint by default)."""
    run = Path(run)
    cfg = run_folder.load_config(run, DynTrainConfig)
    if not cfg.skel_run:
        raise ValueError(f"{run}/config.json names no skel_run; is {run} a `train-dyn` run?")
    skeleton = run_folder.read_skeleton(cfg.skel_run)
    return restore_model(run, cfg, skeleton.parents, skeleton.order, step)


def load_phase2(run: str | Path) -> tuple[Dynamics, DynTrainConfig, Path]:
    """(dynamics model, its config, the phase-1 run folder) of a phase-2 run."""
    model = restore_dynamics(run)
    cfg = run_folder.load_config(run, DynTrainConfig)
    return model, cfg, Path(cfg.skel_run)


def find_vrnn_run(dyn_run: Path, skel_run: Path, inputs: str = "crop") -> Path | None:
    """A positional-baseline phase-2 run beside `dyn_run` trained on the same phase-1 run with
    the same `inputs`."""
    for candidate in sorted(Path(dyn_run).parent.glob("*"), reverse=True):
        if candidate == Path(dyn_run) or not (candidate / run_folder.CONFIG_FILE).is_file():
            continue
        try:
            cfg = run_folder.load_config(candidate, DynTrainConfig)
        except (ValueError, FileNotFoundError, TypeError):
            continue
        same = cfg.skel_run and Path(cfg.skel_run).resolve() == Path(skel_run).resolve()
        same = same and cfg.data.inputs == inputs
        if cfg.model.model == "vrnn" and same and bool(run_folder.checkpoint_steps(candidate)):
            return candidate
    return None


def phase2_runs(run: Path, vrnn_run: str | Path | None) -> tuple[DynTrainConfig, Path, Path | None]:
    """(config of the "nm" run, its phase-1 run, the VRNN run given or found beside it).

    Raises:
      ValueError: `run` is not an "nm" run, or the VRNN run was trained on another phase-1 run.
    """
    dyn_cfg = run_folder.load_config(run, DynTrainConfig)
    if dyn_cfg.model.model != "nm":
        raise ValueError(
            f"{run} is a '{dyn_cfg.model.model}' run; give the Neural Marionette ('nm') run "
            "as --run and the positional baseline as --vrnn-run"
        )
    skel_run = Path(dyn_cfg.skel_run)
    if vrnn_run is None:
        return dyn_cfg, skel_run, find_vrnn_run(run, skel_run, dyn_cfg.data.inputs)
    vrnn_run = Path(vrnn_run)
    vrnn_cfg = run_folder.load_config(vrnn_run, DynTrainConfig)
    vrnn_skel = vrnn_cfg.skel_run
    if not vrnn_skel or Path(vrnn_skel).resolve() != skel_run.resolve():
        raise ValueError(
            f"--vrnn-run {vrnn_run} was trained on the phase-1 run {vrnn_skel}, {run} on "
            f"{skel_run}; compare models of the same skeleton (train the baseline with "
            f"`nmjax train-dyn --model vrnn --skel-run {skel_run}`)"
        )
    if vrnn_cfg.data.inputs != dyn_cfg.data.inputs:
        raise ValueError(
            f"--vrnn-run {vrnn_run} was trained on inputs '{vrnn_cfg.data.inputs}', {run} on "
            f"'{dyn_cfg.data.inputs}'; both methods condition on the same keypoints, so train the "
            f"baseline with `nmjax train-dyn --model vrnn --skel-run {skel_run} --set "
            f"data.inputs={dyn_cfg.data.inputs}`"
        )
    return dyn_cfg, skel_run, vrnn_run
