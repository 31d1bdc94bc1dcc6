"""Phase 1: train the keypoint detector and the affinity (paper Eq. 23); `nmjax train-skel`.

    nmjax train-skel --data synth-arm --preset cpu [--steps N] [--run DIR] [--resume]
                     [--overwrite] [--set model.channels=16 --set weights.vol=1.0 ...]

One jit-compiled step over the pytree `nnx.state((model, optimizer))` (split once, donated).
Periodic validation on the test split (loss terms, SC-score Eq. 21 when joints exist, a picture),
orbax checkpoints (latest few + best validation loss, with the grain iterator position, so
`--resume` continues exactly), metrics to JSONL and TensorBoard. At the end the run folder gets
the artefacts phase 2 needs (contract C10): affinity.npy, keypoint_stats.npz, skeleton.json and
keypoints_{train,test}.npz.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from nmjax import io, losses, metrics
from nmjax.config import (
    DATASETS,
    PRESETS,
    SkelTrainConfig,
    add_override_argument,
    apply_overrides,
    dataset_spec,
    skel_preset,
)
from nmjax.models.detector import KeypointDetector, check_detector_config
from nmjax.train import common, parallel

BEST_METRIC = "val/loss"


class NonFiniteLossError(RuntimeError):
    """The training loss became NaN or infinite."""


# --- configuration -----------------------------------------------------------------------------


def check_config(cfg: SkelTrainConfig) -> None:
    """Refuses (ValueError naming the field) a configuration that cannot train, before compiling."""
    check_detector_config(cfg.model)
    if cfg.data.frames < 3:
        raise ValueError(
            f"data.frames (T) must be >= 3 (the trajectory loss needs accelerations), got "
            f"{cfg.data.frames}"
        )
    if cfg.data.grid != cfg.model.grid:
        raise ValueError(
            f"data.grid ({cfg.data.grid}) and model.grid ({cfg.model.grid}) must be equal; set "
            "both (e.g. --set data.grid=32 --set model.grid=32)"
        )
    if cfg.data.batch_size < 1:
        raise ValueError(f"data.batch_size must be >= 1, got {cfg.data.batch_size}")
    for name in ("steps", "log_every", "val_every", "val_batches", "ckpt_every"):
        if getattr(cfg, name) < 1:
            raise ValueError(f"{name} must be >= 1, got {getattr(cfg, name)}")
    if not cfg.time_limit_minutes >= 0:
        raise ValueError(
            f"time_limit_minutes must be >= 0 (0: no limit), got {cfg.time_limit_minutes}"
        )


# --- model, state and the compiled steps -------------------------------------------------------


def build(cfg: SkelTrainConfig, seed: int | None = None):
    """(graphdef, state) of the detector and its optimizer, initialised from `seed`."""
    model = KeypointDetector(cfg.model, rngs=nnx.Rngs(cfg.seed if seed is None else seed))
    tx = common.make_optimizer(cfg.learning_rate, cfg.lr_milestones, cfg.lr_decay, cfg.clip_norm)
    optimizer = nnx.Optimizer(model, tx, wrt=nnx.Param)
    return nnx.split((model, optimizer))


class Steps:
    """The jit-compiled train and eval steps of one configuration, data-parallel on `mesh`.

    Batches are sharded over the mesh's "data" axis, the state and all outputs replicated
    (`nmjax.train.parallel`); the default mesh spans every device. `train_traces` counts how often
    the train step was traced (it must stay 1).
    """

    def __init__(self, graphdef: Any, cfg: SkelTrainConfig, mesh: jax.sharding.Mesh | None = None):
        self.graphdef, self.weights = graphdef, cfg.weights
        self.mesh = parallel.data_mesh() if mesh is None else mesh
        self.train_traces = 0
        self.train = jax.jit(self._train, donate_argnums=0)
        self.eval = jax.jit(self._eval)

    def _train(
        self, state: Any, voxels: jax.Array, joints: jax.Array | None = None
    ) -> tuple[Any, dict[str, jax.Array]]:
        self.train_traces += 1
        voxels, joints = parallel.constrain_batch((voxels, joints), self.mesh)
        model, optimizer = nnx.merge(self.graphdef, state)

        def loss_fn(model: KeypointDetector):
            return losses.skeleton_loss(_with_joints(model(voxels), joints), self.weights)

        (loss, terms), grads = nnx.value_and_grad(loss_fn, has_aux=True)(model)
        optimizer.update(model, grads)
        scalars = {"loss": loss, "grad_norm": optax.tree.norm(grads), **terms}
        return parallel.constrain_replicated((nnx.state((model, optimizer)), scalars), self.mesh)

    def _eval(
        self, state: Any, voxels: jax.Array, joints: jax.Array | None = None
    ) -> tuple[dict[str, jax.Array], jax.Array]:
        voxels, joints = parallel.constrain_batch((voxels, joints), self.mesh)
        model, _ = nnx.merge(self.graphdef, state)
        out = model(voxels)
        loss, terms = losses.skeleton_loss(_with_joints(out, joints), self.weights)
        return parallel.constrain_replicated(({"loss": loss, **terms}, out["keypoints"]), self.mesh)


_STEPS_CACHE: dict[tuple[Any, ...], Steps] = {}


def get_steps(graphdef: Any, cfg: SkelTrainConfig, mesh: jax.sharding.Mesh | None = None) -> Steps:
    """The compiled steps of this configuration, shared within a process (a second run in the
    same process, e.g. a resume in a notebook or a test, compiles nothing).

    Keyed by everything that shapes the graph: model, loss weights, optimizer settings and the
    mesh (default: all devices); states built from the same settings merge with the first run's
    graphdef.
    """
    mesh = parallel.data_mesh() if mesh is None else mesh
    key = (cfg.model, cfg.weights, cfg.learning_rate, cfg.lr_milestones, cfg.lr_decay)
    key += (cfg.clip_norm, mesh)
    if key not in _STEPS_CACHE:
        _STEPS_CACHE[key] = Steps(graphdef, cfg, mesh)
    return _STEPS_CACHE[key]


def _with_joints(outputs: dict[str, jax.Array], joints: jax.Array | None) -> dict:
    return outputs if joints is None else {**outputs, "joints": joints}


def supervision(steps: Steps, batch: dict[str, np.ndarray]) -> np.ndarray | None:
    """The batch's ground-truth joints when the loss is joint-supervised (vol_target="joints")."""
    if steps.weights.vol_target != "joints":
        return None
    if "joints" not in batch:
        raise ValueError("weights.vol_target='joints' needs a dataset with ground-truth joints")
    return batch["joints"]


def step_inputs(
    steps: Steps, batch: dict[str, np.ndarray], *, host_slice: bool = True
) -> tuple[jax.Array, jax.Array | None]:
    """(voxels, joints or None) of a batch as global arrays sharded over `steps.mesh`.

    `host_slice`: the batch is this host's slice of the global batch (training); otherwise every
    host holds the whole batch (validation).
    """
    inputs = (batch["voxels"], supervision(steps, batch))
    if host_slice:
        return parallel.host_batch_to_global(inputs, steps.mesh)
    return parallel.global_array(inputs, steps.mesh)


def model_of(graphdef: Any, state: Any) -> KeypointDetector:
    return nnx.merge(graphdef, state)[0]


def abstract_state(state: Any) -> Any:
    """Shapes, dtypes and shardings of `state`: a restore target that keeps its placement."""
    return jax.tree.map(
        lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=getattr(x, "sharding", None)),
        state,
    )


# --- validation --------------------------------------------------------------------------------


def validate(
    steps: Steps, state: Any, batches: list[dict[str, np.ndarray]]
) -> tuple[dict[str, float], np.ndarray]:
    """Mean loss terms over `batches` (prefixed "val/"), SC-score when joints exist.

    Returns (scalars, keypoints of every batch stacked (num_batches, B, T, K, 4)).
    """
    sums: dict[str, float] = {}
    sc = metrics.SemanticConsistency()
    all_kp = []
    for batch in batches:
        terms, keypoints = steps.eval(state, *step_inputs(steps, batch, host_slice=False))
        for name, value in terms.items():
            sums[name] = sums.get(name, 0.0) + float(value)
        if "joints" in batch:
            sc.update(keypoints, batch["joints"])
        all_kp.append(np.asarray(keypoints))
    scalars = {f"val/{k}": v / len(batches) for k, v in sums.items()}
    if sc.frames > 0:
        scalars["val/sc_score"] = sc.result()  # the published definition (DESIGN §9)
        scalars["val/sc_fixed_nodes"] = sc.result("fixed")
    return scalars, np.stack(all_kp)


# --- the training loop -------------------------------------------------------------------------


def default_run_dir(data: str) -> Path:
    stamp = datetime.datetime.now(datetime.UTC).strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"skel-{data}-{stamp}"


def train(
    cfg: SkelTrainConfig,
    run_dir: str | Path,
    *,
    resume: bool = False,
    overwrite: bool = False,
    finalize: bool = True,
    export: bool = True,
    progress: bool = True,
    step_hook: Callable[[int, Any], Any] | None = None,
) -> dict[str, Any]:
    """Trains phase 1 into `run_dir` until `cfg.steps`; returns a summary dict.

    Args:
      cfg: the full configuration (checked before anything is compiled).
      run_dir: the run folder (contract C10).
      resume: continue from the latest checkpoint of `run_dir` (state, step, data position).
      overwrite: replace an existing `run_dir`.
      finalize: write affinity.npy, keypoint_stats.npz, skeleton.json, keypoints_*.npz at the end.
      export: with `finalize`, also export keypoints_{train,test}.npz (phase 2 reads them; a
        study that only scores the detector can skip the pass over every sequence).
      progress: show a tqdm bar.
      step_hook: test hook `(step, state) -> state` applied before each step (step = steps
        done so far).

    Raises:
      NonFiniteLossError: the loss became NaN/inf; the message gives the step, and the last good
        checkpoint stays on disk.
    """
    from tqdm import tqdm

    from nmjax.data import pipeline

    check_config(cfg)
    if cfg.time_limit_minutes > 0 and jax.process_count() > 1:
        # Each host would read its own clock and could stop one step before the others.
        raise ValueError("time_limit_minutes works in single-process runs only; set steps instead")
    mesh = parallel.data_mesh()
    parallel.check_batch_size(
        cfg.data.batch_size, "data.batch_size", mesh, "--set data.batch_size="
    )
    run = parallel.prepare_run_dir(run_dir, resume=resume, config=cfg, overwrite=overwrite)
    graphdef, state = build(cfg)
    state = parallel.replicate(state, mesh)
    steps = get_steps(graphdef, cfg, mesh)
    graphdef = steps.graphdef
    data_iter = pipeline.skel_iterator(cfg.data, "train", seed=cfg.seed)
    val_batches = pipeline.eval_batches(cfg.data, "test", cfg.val_batches, seed=cfg.seed)
    ckpt = common.Checkpointer(run / "checkpoints", cfg.keep_checkpoints, best_metric=BEST_METRIC)
    start = 0
    if resume:
        if ckpt.latest_step() is None:
            raise FileNotFoundError(
                f"cannot resume {run}: it has no checkpoint yet; start it again with --overwrite"
            )
        start, state = ckpt.restore(abstract_state(state), data_iter=data_iter)
    writer = parallel.metric_writer(run, resume_step=start if resume else None)
    summary: dict[str, Any] = {"run": str(run), "start_step": start}
    pbar = tqdm(total=cfg.steps, initial=start, disable=not progress, dynamic_ncols=True)
    t_last, step_last = time.perf_counter(), start
    deadline = t_last + 60.0 * cfg.time_limit_minutes if cfg.time_limit_minutes > 0 else math.inf
    last_val: dict[str, float] = {}
    try:
        step, last = start, start >= cfg.steps
        while not last:
            batch = next(data_iter)
            if step_hook is not None:
                state = step_hook(step, state)
            state, scalars = steps.train(state, *step_inputs(steps, batch))
            step += 1
            loss = float(scalars["loss"])
            if not math.isfinite(loss):
                raise NonFiniteLossError(
                    f"loss became {loss} at step {step}; training stopped. The last good "
                    f"checkpoint (step {ckpt.latest_step()}) in {run / 'checkpoints'} is kept; "
                    "lower learning_rate or clip_norm and resume or restart"
                )
            pbar.update(1)
            last = step >= cfg.steps or time.perf_counter() >= deadline
            if step % cfg.log_every == 0 or last:
                now = time.perf_counter()
                rate = (step - step_last) / max(now - t_last, 1e-9)
                t_last, step_last = now, step
                logged = {f"train/{k}": float(v) for k, v in scalars.items()}
                logged["train/steps_per_s"] = rate
                writer.write_scalars(step, logged)
                pbar.set_postfix(loss=f"{loss:.4g}", steps_s=f"{rate:.2f}")
            val_metrics = None
            if step % cfg.val_every == 0 or last:
                val_metrics, val_kp = validate(steps, state, val_batches)
                last_val = val_metrics
                writer.write_scalars(step, val_metrics)
                _validation_figure(run, step, graphdef, state, val_batches, val_kp)
                pbar.write(
                    f"step {step}: "
                    + " ".join(f"{k[4:]}={v:.4g}" for k, v in sorted(val_metrics.items()))
                )
            if step % cfg.ckpt_every == 0 or last:
                if step not in ckpt.all_steps():
                    ckpt.save(step, state, metrics=val_metrics, data_iter=data_iter)
        summary.update(
            step=step,
            stopped_by_time_limit=step < cfg.steps,
            train_traces=steps.train_traces,
            **last_val,
        )
    finally:
        pbar.close()
        writer.close()
        ckpt.close()
    if finalize:
        write_artifacts(run, graphdef, state, val_batches, steps, export=export)
    return summary


def _validation_figure(run, step, graphdef, state, val_batches, val_kp) -> None:
    from nmjax import viz

    affinity = np.asarray(model_of(graphdef, state).affinity())  # on every host: a collective
    if not parallel.is_primary():
        return
    viz.plot_keypoints(
        run / "figures" / f"keypoints_{step:07d}.png",
        val_batches[0]["voxels"][0, 0],
        val_kp[0, 0, 0],
        affinity,
        title=f"step {step}",
    )


# --- artefacts for the later stages (contract C10) ---------------------------------------------


def write_artifacts(
    run: Path, graphdef: Any, state: Any, val_batches, steps: Steps, export: bool = True
) -> None:
    """affinity.npy, keypoint_stats.npz, then skeleton.json and (with `export`)
    keypoints_{train,test}.npz.

    Every host takes part in the computations on the (global) state; only process 0 writes.
    """
    model = model_of(graphdef, state)
    affinity = np.asarray(model.affinity(), np.float32)
    _, keypoints = validate(steps, state, val_batches)
    if not parallel.is_primary():
        return
    io.save_npy(run / "affinity.npy", affinity)
    flat = keypoints.reshape(-1, *keypoints.shape[-2:])  # (frames, K, 4)
    io.save_npz(
        run / "keypoint_stats.npz",
        intensities=flat[:, :, 3].mean(axis=0).astype(np.float32),
        rest_positions=flat[:, :, :3].mean(axis=0).astype(np.float32),
        example_voxels=np.asarray(val_batches[0]["voxels"][0, 0], np.float32),
        example_keypoints=keypoints[0, 0, 0].astype(np.float32),
    )
    try:
        from nmjax.skeleton_cli import extract_run_skeleton

        extract_run_skeleton(run)
    except Exception as err:  # the skeleton stage is separate; training results stay valid
        print(
            f"train-skel: skeleton extraction failed ({type(err).__name__}: {err}); run "
            f"`nmjax extract-skeleton --run {run}` once fixed",
            file=sys.stderr,
        )
    for split in ("train", "test") if export else ():
        export_keypoints(run, split, model=model)


def load_detector(run_dir: str | Path, step: int | None = None):
    """The trained detector of a phase-1 run: (model, cfg).

    Restores `step`, else the best checkpoint by validation loss, else the latest.
    """
    run = Path(run_dir)
    cfg = common.load_config(run, SkelTrainConfig)
    graphdef, state = build(cfg)
    ckpt = common.Checkpointer(run / "checkpoints", cfg.keep_checkpoints, best_metric=BEST_METRIC)
    try:
        if step is None:
            step = ckpt.best_step() or ckpt.latest_step()
        _, state = ckpt.restore(abstract_state(state), step=step)
    finally:
        ckpt.close()
    return model_of(graphdef, state), cfg


def sequence_windows(voxels: np.ndarray, frames: int) -> np.ndarray:
    """(S, G, G, G) -> (ceil(S / T), T, G, G, G); the last window padded with the last frame."""
    s = voxels.shape[0]
    windows = -(-s // frames)
    pad = windows * frames - s
    if pad:
        voxels = np.concatenate([voxels, np.repeat(voxels[-1:], pad, axis=0)], axis=0)
    return voxels.reshape(windows, frames, *voxels.shape[1:])


def export_keypoints(
    run_dir: str | Path,
    split: str,
    *,
    model: KeypointDetector | None = None,
    data_root: str | Path | None = None,
    path: str | Path | None = None,
) -> Path:
    """Writes `<run>/keypoints_<split>.npz`: one (S, K, 4) array per sequence of the split.

    Each whole sequence (every `sample_rate`-th frame) is normalised with one bounding box
    (DESIGN section 4), voxelised, cut into consecutive windows of T frames (the last padded by
    repeating the last frame) and run through the detector in jit-compiled batches of B windows.
    `data_root` reads the sequences from another copy of the run's dataset (e.g. a set of
    longer synthetic sequences), `path` writes the file elsewhere.
    """
    from nmjax.data.datasets import load_sequences
    from nmjax.data.voxelize import normalize_sequence, voxelize

    run = Path(run_dir)
    cfg = common.load_config(run, SkelTrainConfig)
    if model is None:
        model, cfg = load_detector(run)
    graphdef, state = nnx.split(model)
    state = parallel.to_local(state)  # a trained state may be replicated over several hosts

    @jax.jit
    def detect(state, voxels):
        return nnx.merge(graphdef, state).detect(voxels)[1]

    t, b = cfg.data.frames, cfg.data.batch_size
    arrays = {}
    root = cfg.data.root if data_root is None else data_root
    for seq in load_sequences(cfg.data.name, split, root):
        points = np.asarray(seq.vertices[:: cfg.data.sample_rate], np.float32)
        points, _ = normalize_sequence(points)
        windows = sequence_windows(voxelize(points, cfg.data.grid), t)
        n = windows.shape[0]
        padded = -(-n // b) * b  # whole batches: one compiled shape
        if padded > n:
            windows = np.concatenate([windows, np.repeat(windows[-1:], padded - n, axis=0)])
        chunks = [
            np.asarray(detect(state, jnp.asarray(windows[i : i + b]))) for i in range(0, padded, b)
        ]
        keypoints = np.concatenate(chunks).reshape(-1, *chunks[0].shape[2:])
        arrays[seq.name] = keypoints[: points.shape[0]].astype(np.float32)
    path = run / f"keypoints_{split}.npz" if path is None else Path(path)
    io.save_npz(path, **arrays)
    return path


# --- command line ------------------------------------------------------------------------------


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="nmjax train-skel",
        description="Phase 1: train the keypoint detector and affinity (paper Eq. 23).",
    )
    parser.add_argument("--data", default="synth-hand", help=f"one of {', '.join(DATASETS)}")
    parser.add_argument("--preset", default="default", choices=PRESETS)
    parser.add_argument("--steps", type=int, default=None, help="total optimizer steps")
    parser.add_argument("--run", default=None, help="run folder (default runs/skel-DATA-STAMP)")
    parser.add_argument("--resume", action="store_true", help="continue --run from its checkpoint")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --run")
    parser.add_argument("--root", default=None, help="dataset folder (default data/DATA)")
    add_override_argument(
        parser, "override any config field, e.g. --set model.channels=16 --set weights.vol=1.0"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parallel.add_distributed_args(parser)
    return parser.parse_args(list(argv))


def config_from_args(args: argparse.Namespace) -> SkelTrainConfig:
    """The preset (or, with --resume, the run's saved config) plus the command-line overrides."""
    if args.resume:
        if args.run is None:
            raise ValueError("--resume needs --run DIR (the run folder to continue)")
        cfg = common.load_config(args.run, SkelTrainConfig)
    else:
        dataset_spec(args.data)  # unknown names list the valid ones
        cfg = skel_preset(args.data, args.preset)
    if args.root is not None:
        cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, root=args.root))
    cfg = apply_overrides(cfg, args.overrides)
    if args.steps is not None:
        cfg = dataclasses.replace(cfg, steps=args.steps)
    if args.run is not None:
        cfg = dataclasses.replace(cfg, run=str(args.run))
    check_config(cfg)
    return cfg


def main(argv: Sequence[str]) -> int:
    args = parse_args(argv)
    try:
        parallel.initialize_distributed(
            args.coordinator_address, args.num_processes, args.process_id
        )
        cfg = config_from_args(args)
    except (ValueError, FileNotFoundError) as err:
        print(f"train-skel: {err}", file=sys.stderr)
        return 2
    run = Path(cfg.run) if cfg.run else default_run_dir(cfg.data.name)
    try:
        summary = train(
            cfg, run, resume=args.resume, overwrite=args.overwrite, progress=not args.no_progress
        )
    except (ValueError, FileNotFoundError, NonFiniteLossError) as err:
        print(f"train-skel: {err}", file=sys.stderr)
        return 1
    print(json.dumps(summary, indent=1, default=float))
    return 0
