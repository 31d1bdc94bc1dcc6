"""Phase 1: train the keypoint detector and the affinity (paper Eq. 23).

One module-level jit-compiled step (`train_step`) over the state {"model", "opt"} (graphdef and
settings static, the state donated), driven by `loop.train_loop`: periodic validation on the
test split (loss terms, SC-score Eq. 21 when joints exist, a picture), orbax checkpoints (latest
few + best validation loss, with the grain iterator position, so a resume continues exactly),
metrics to JSONL and TensorBoard; `train_skeleton` is the entry, and it leaves a complete
phase-1 run: affinity.npy and keypoint_stats.npz of the best checkpoint, then skeleton.json and
keypoints_{train,test}.npz of the same detector (`trained.complete_phase1`; contract C10,
`nmjax.run_folder`). The trained detector restored for inference (`trained.Detector`) is
`nmjax.train.trained`'s.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from nmjax import keypoints as kp_lib
from nmjax import losses, metrics, run_folder
from nmjax.config import LossWeights, SkelTrainConfig, resolve_epochs
from nmjax.data.pipeline import Augmentation
from nmjax.models.detector import KeypointDetector, check_detector_config
from nmjax.train import checkpoints, loop, optim, parallel, trained

BEST_METRIC = trained.BEST_METRIC
NonFiniteLossError = loop.NonFiniteLossError


# --- configuration -----------------------------------------------------------------------------


def check_config(cfg: SkelTrainConfig) -> None:
    """Refuses (ValueError naming the field) a configuration that cannot train, before compiling."""
    check_detector_config(cfg.model)
    Augmentation.from_config(cfg.data)  # refuses out-of-range augmentation options
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
    loop.check_positive({"data.batch_size": cfg.data.batch_size})
    loop.check_loop(cfg.loop)
    loop.check_positive({"val_batches": cfg.val_batches})
    optim.check_schedule(cfg.optim, cfg.loop)


# --- model, state and the compiled steps -------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class StepSettings:
    """What the compiled steps depend on besides the graph (hashable: a static jit argument)."""

    weights: LossWeights
    optimizer: optim.OptimizerSettings

    @classmethod
    def of(cls, cfg: SkelTrainConfig) -> StepSettings:
        return cls(cfg.weights, optim.OptimizerSettings.of(cfg))


def build(cfg: SkelTrainConfig, seed: int | None = None) -> tuple[nnx.GraphDef, dict[str, Any]]:
    """(graphdef, {"model", "opt"}) of the detector and its optimizer, initialised from `seed`."""
    return optim.init_state(trained.build_detector(cfg, seed), StepSettings.of(cfg).optimizer)


# The fields the detector's weights' shapes follow: a run that starts from another run's weights
# (`init_from`) must have the same.
INIT_FIELDS = (
    "model.grid",
    "model.heatmap_stride",
    "model.num_keypoints",
    "model.channels",
    "model.hourglass_channels",
    "model.num_affinity",
)


def initial_weights(cfg: SkelTrainConfig) -> nnx.State:
    """The weights a fine-tuning run of `cfg` starts from: the trained detector of the run
    `cfg.init_from` (restored as the later stages restore it: the
    best checkpoint, the weight average when the run keeps one; `restore_detector`).

    Raises:
      FileNotFoundError, ValueError: one line; the source is no phase-1 run with a checkpoint,
        or its network differs from `cfg`'s (`checkpoints.init_source_config`).
    """
    checkpoints.init_source_config(cfg, INIT_FIELDS, "phase-1")
    model, _ = trained.restore_detector(cfg.init_from)
    return nnx.state(model)


def loss_fn(
    model: KeypointDetector, batch: dict[str, jax.Array], weights: LossWeights
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Eq. 23 on a batch {"voxels": (B, T, G, G, G)[, "joints": (B, T, J, 3)]}."""
    return losses.skeleton_loss({**batch, **model(batch["voxels"])}, weights)


@functools.partial(
    jax.jit, static_argnames=("graphdef", "settings", "mesh"), donate_argnames="state"
)
def train_step(state, batch, *, graphdef, settings: StepSettings, mesh):
    """One data-parallel optimizer step of Eq. 23.

    Args:
      state: {"model": nnx.State of the detector, "opt": optax state of its nnx.Param[, "ema":
        the weight average's optax.ema state]} (donated).
      batch: `device_batch` output, sharded over the mesh's "data" axis.
      graphdef: the detector's nnx.GraphDef (static; equal for equal configurations, so a new
        run of the same configuration reuses the compiled step).
      settings: StepSettings (static).
      mesh: the data mesh (static, `parallel.data_mesh`).

    Returns:
      (new state, metrics: loss, grad_norm, the unweighted terms and the fusion weights),
      replicated.
    """
    batch = parallel.constrain_batch(batch, mesh)
    model = nnx.merge(graphdef, state["model"])
    grad_fn = nnx.value_and_grad(loss_fn, has_aux=True)
    (loss, terms), grads = grad_fn(model, batch, settings.weights)
    state = optim.apply_gradients(model, grads, state, settings.optimizer)
    scalars = {"loss": loss, "grad_norm": optax.tree.norm(grads), **terms, **fusion(model)}
    return parallel.constrain_replicated((state, scalars), mesh)


def fusion(model: KeypointDetector) -> dict[str, jax.Array]:
    """The heatmap fusion z = w_frame h + w_st h_st + b, logged so that a run shows how much each
    branch contributes (both weights start near 0, N(0, 0.02^2), the bias at 0)."""
    kernel, bias = model.fuse.kernel[...], model.fuse.bias[...]
    return {"fuse_w_frame": kernel[0, 0], "fuse_w_st": kernel[1, 0], "fuse_b": bias[0]}


@functools.partial(jax.jit, static_argnames=("graphdef", "settings", "mesh"))
def eval_step(state, batch, *, graphdef, settings: StepSettings, mesh):
    """Loss terms and keypoints (B, T, K, 4) of a validation batch (by the weight average when
    the run keeps one)."""
    batch = parallel.constrain_batch(batch, mesh)
    model = optim.trained_model(graphdef, state, settings.optimizer.ema_decay)
    out = model(batch["voxels"])
    loss, terms = losses.skeleton_loss({**batch, **out}, settings.weights)
    # The median share of a heatmap's mass beyond 1.5 cells of its peak (the softplus floor).
    terms["heat_far_mass"] = jnp.median(kp_lib.heatmap_far_mass(out["heatmaps"]))
    return parallel.constrain_replicated(({"loss": loss, **terms}, out["keypoints"]), mesh)


def make_steps(
    graphdef: nnx.GraphDef, cfg: SkelTrainConfig, mesh: jax.sharding.Mesh | None = None
) -> tuple[Callable[..., Any], Callable[..., Any]]:
    """(`train_step`, `eval_step`) bound to a model, configuration and mesh (default: all
    devices): `(state, batch)`."""
    mesh = parallel.data_mesh() if mesh is None else mesh
    bound = {"graphdef": graphdef, "settings": StepSettings.of(cfg), "mesh": mesh}
    return functools.partial(train_step, **bound), functools.partial(eval_step, **bound)


def device_batch(
    batch: dict[str, np.ndarray],
    cfg: SkelTrainConfig,
    mesh: jax.sharding.Mesh,
    *,
    host_slice: bool = True,
) -> dict[str, jax.Array]:
    """The step's inputs of a pipeline batch as global arrays sharded over `mesh`: the voxels,
    plus the ground-truth joints when the loss is joint-supervised (vol_target="joints").

    `host_slice`: the batch is this host's slice of the global batch (training); otherwise every
    host holds the whole batch (validation).
    """
    inputs = {"voxels": batch["voxels"]}
    if cfg.weights.vol_target == "joints":
        if "joints" not in batch:
            raise ValueError("weights.vol_target='joints' needs a dataset with ground-truth joints")
        inputs["joints"] = batch["joints"]
    if host_slice:
        return parallel.host_batch_to_global(inputs, mesh)
    return parallel.global_array(inputs, mesh)


def model_of(graphdef: Any, state: Any, cfg: SkelTrainConfig) -> KeypointDetector:
    """The trained detector of a training state (`optim.trained_model`)."""
    return optim.trained_model(graphdef, state, cfg.optim.ema_decay)


abstract_state = checkpoints.abstract_state


# --- validation --------------------------------------------------------------------------------


def validate(
    eval_fn: Callable[..., Any],
    cfg: SkelTrainConfig,
    mesh: jax.sharding.Mesh,
    state: Any,
    batches: list[dict[str, np.ndarray]],
) -> tuple[dict[str, float], np.ndarray]:
    """Mean loss terms over `batches` (prefixed "val/"), SC-score when joints exist.

    Args:
      eval_fn: the bound `eval_step` of `make_steps`.

    Returns:
      (scalars, keypoints of every batch stacked (num_batches, B, T, K, 4)).
    """
    sums: dict[str, float] = {}
    sc = metrics.SemanticConsistency()
    all_kp = []
    for batch in batches:
        terms, keypoints = eval_fn(state, device_batch(batch, cfg, mesh, host_slice=False))
        for name, value in jax.device_get(terms).items():
            sums[name] = sums.get(name, 0.0) + float(value)
        if "joints" in batch:
            sc.update(keypoints, batch["joints"])
        all_kp.append(np.asarray(keypoints))
    scalars = {f"val/{k}": v / len(batches) for k, v in sums.items()}
    if sc.frames > 0:
        scalars["val/sc_score"] = sc.result()  # the published definition (docs/architecture.md §9)
        scalars["val/sc_fixed_nodes"] = sc.result("fixed")
    return scalars, np.stack(all_kp)


# --- the training loop -------------------------------------------------------------------------


def train_skeleton(
    cfg: SkelTrainConfig,
    *,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = True,
    step_hook: Callable[[int, Any], Any] | None = None,
    finalize: bool = True,
) -> loop.TrainSummary:
    """Phase 1's entry: trains the detector into the run folder `cfg.run` until `cfg.loop.steps`.

    The run folder is `cfg.run`, else a new one under the run root
    (`run_folder.config_run_dir`); the epochs count the training sequences
    (`config.resolve_epochs`), as `dyn.train_dynamics` counts its own.

    Args:
      cfg: the full configuration (checked before anything is compiled or written).
      resume: continue from the latest checkpoint of the run folder (state, step, data
        position); its config.json may differ from `cfg` only in `run_folder.RESUMABLE_FIELDS`.
        Without it a run with `cfg.init_from` starts from that run's weights
        (`initial_weights`) and a fresh optimizer.
      overwrite: replace a run folder that holds files (refused without it or `resume`).
      progress: show a tqdm bar.
      step_hook: test hook `(step, state) -> state` applied before each step (step = steps
        done so far).
      finalize: complete the run folder at the end from the best checkpoint: affinity.npy and
        keypoint_stats.npz (`write_artifacts`), then skeleton.json and
        keypoints_{train,test}.npz (`trained.complete_phase1`); False leaves the checkpoints
        and logs only (tests of the loop itself).

    Raises:
      NonFiniteLossError: the loss became NaN/inf; the message gives the step, and the last good
        checkpoint stays on disk.
    """
    from nmjax.data import pipeline
    from nmjax.data.datasets import load_sequences
    from nmjax.data.synthetic import ensure_dataset

    check_config(cfg)
    if cfg.loop.time_limit_minutes > 0 and jax.process_count() > 1:
        # Each host would read its own clock and could stop one step before the others.
        raise ValueError("time_limit_minutes works in single-process runs only; set steps instead")
    mesh = parallel.data_mesh()
    parallel.check_batch_size(cfg.data.batch_size, "data.batch_size", mesh, "--batch-size ")
    run_dir = run_folder.config_run_dir(cfg.run, "skel", cfg.data.name)
    # A synthetic set is generated on first use here, explicitly: the loaders never write.
    ensure_dataset(cfg.data.name, cfg.data.root)
    train_sequences = len(load_sequences(cfg.data.name, "train", cfg.data.root))
    cfg = resolve_epochs(cfg, train_sequences, cfg.data.batch_size)
    data_iter = pipeline.skel_iterator(cfg.data, "train", seed=cfg.seed)
    val_batches = pipeline.eval_batches(cfg.data, "test", cfg.val_batches, seed=cfg.seed)
    graphdef, state = build(cfg)
    if cfg.init_from and not resume:  # checked before the run folder is made
        state["model"] = checkpoints.checked_weights(
            initial_weights(cfg), state["model"], cfg.init_from
        )
    run = parallel.prepare_run_dir(run_dir, resume=resume, config=cfg, overwrite=overwrite)
    state = parallel.replicate(state, mesh)
    step_fn, eval_fn = make_steps(graphdef, cfg, mesh)

    def train_step(state: Any, step: int) -> tuple[Any, dict[str, jax.Array]]:
        del step  # the data iterator is the only source of randomness
        return step_fn(state, device_batch(next(data_iter), cfg, mesh))

    def validate_and_draw(step: int, state: Any) -> dict[str, float]:
        scalars, keypoints = validate(eval_fn, cfg, mesh, state, val_batches)
        _validation_figure(run, step, model_of(graphdef, state, cfg), val_batches, keypoints)
        return scalars

    end = loop.train_loop(
        state,
        run,
        resume=resume,
        loop=cfg.loop,
        train_step=train_step,
        validate=validate_and_draw,
        best_metric=BEST_METRIC,
        data_iter=data_iter,
        progress=progress,
        step_hook=step_hook,
    )
    if finalize:
        write_artifacts(run, graphdef, best_state(run, end.state, cfg), val_batches, cfg)
        trained.complete_phase1(run)
    return loop.TrainSummary.of(run, end, cfg.loop)


def best_state(run: Path, state: Any, cfg: SkelTrainConfig) -> Any:
    """The training state of the run's best checkpoint (lowest validation loss), placed as
    `state` is (replicated over the mesh); `state` itself when no checkpoint holds a validation."""
    with checkpoints.Checkpointer.of_run(run, cfg.loop, BEST_METRIC) as ckpt:
        best = ckpt.best_step()
        if best is None:
            return state
        _, restored = ckpt.restore(checkpoints.abstract_state(state), step=best)
    return restored


def _validation_figure(run, step, model, val_batches, val_kp) -> None:
    from nmjax import viz

    affinity = np.asarray(model.affinity())  # on every host: a collective
    if not parallel.is_primary():
        return
    viz.plot_keypoints(
        run / run_folder.FIGURES_DIR / f"keypoints_{step:07d}.png",
        val_batches[0]["voxels"][0, 0],
        val_kp[0, 0, 0],
        affinity,
        title=f"step {step}",
    )


# --- artefacts for the later stages (contract C10) ---------------------------------------------


def write_artifacts(
    run: Path, graphdef: Any, state: Any, val_batches, cfg: SkelTrainConfig
) -> None:
    """affinity.npy and keypoint_stats.npz (the inputs of skeleton extraction) of `state`, which
    `train_skeleton` takes from the best checkpoint (`best_state`): the detector `Detector.load`
    restores, so the skeleton and the exported keypoints come from one model.

    Every host takes part in the computations on the (global) state; only process 0 writes.
    """
    mesh = parallel.data_mesh()
    affinity = np.asarray(model_of(graphdef, state, cfg).affinity(), np.float32)
    _, keypoints = validate(make_steps(graphdef, cfg, mesh)[1], cfg, mesh, state, val_batches)
    if not parallel.is_primary():
        return
    example_voxels = val_batches[0]["voxels"][0, 0]
    run_folder.write_phase1_artifacts(run, affinity, keypoints, example_voxels)
