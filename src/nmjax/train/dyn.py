"""Phase 2: train the dynamics module (VRNN) on the keypoint trajectories of a phase-1 run.

`train_dynamics` is the entry. It reads a phase-1 run folder (contract C10, `nmjax.run_folder`):
`skeleton.json` (parents, root, order) and the frozen detector's keypoints, by
`DynTrainConfig.data.inputs` the detector on each crop ("crop", the release's) or the exported
whole-sequence keypoints ("sequence"); `dyn_inputs` builds both (`dyn_inputs.Phase2Inputs`).

The crops of step s are the starts drawn with the key fold_in(seed key, s) (`crop_draws`, a block
of steps at a time on the host, so a lazily detected crop is known before its step runs), so a
resumed run sees exactly the batches of an uninterrupted one without saving a data-iterator
state. The step and the loop are those of phase 1 (`loop.train_loop`); only `loss_fn` and the
data differ.

Loss: Eq. 3 (`losses.vrnn_reconstruction`) + kl_weight * Eq. 4, the KL reduced as the authors'
release reduces it: the mean over batch, time and latent dimension of the per-dimension KL
(`losses.kl_diag_gaussians(..., axis=None)`), with the released weight 0.003. Summing over the
D_z latent dimensions instead would weigh the KL D_z times more (128 at the paper's size).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from nmjax import losses, run_folder
from nmjax.config import DYN_INPUTS, DynTrainConfig, resolve_epochs
from nmjax.models.dynamics import Dynamics
from nmjax.train import checkpoints, dyn_inputs, loop, optim, parallel, trained

# --- the crops each step draws -----------------------------------------------------------------


# Steps whose draws `CropDraws` computes at once: one small program per block instead of a
# host-device round trip per step.
DRAW_BLOCK = 256


@functools.partial(jax.jit, static_argnames=("batch_size", "count"))
def crop_draws(
    base_key: jax.Array,
    first_step: jax.Array,
    num_starts: jax.Array,
    *,
    batch_size: int,
    count: int,
) -> jax.Array:
    """(count, B) indices into the starts, drawn uniformly for steps first_step, ... (jittable).

    Step s draws with the first half of split(fold_in(base_key, s)); the step's model noise uses
    the second half (`train_step`), so the draws depend on nothing but the seed and the step.
    """

    def draw(step: jax.Array) -> jax.Array:
        key_data, _ = jax.random.split(jax.random.fold_in(base_key, step))
        return jax.random.randint(key_data, (batch_size,), 0, num_starts)

    return jax.vmap(draw)(first_step + jnp.arange(count, dtype=jnp.int32))


class CropDraws:
    """The start indices each step draws (`crop_draws`), computed a block of steps at a time."""

    def __init__(
        self, base_key: jax.Array, num_starts: int, batch_size: int, block: int = DRAW_BLOCK
    ):
        self.base_key, self.num_starts, self.batch_size, self.block = (
            base_key,
            num_starts,
            batch_size,
            block,
        )
        self._first, self._draws = -1, np.zeros((0, batch_size), np.int32)

    def at(self, step: int) -> np.ndarray:
        """(B,) the indices step `step` draws."""
        if not self._first <= step < self._first + len(self._draws):
            self._first = step - step % self.block
            self._draws = np.asarray(
                crop_draws(
                    self.base_key,
                    jnp.int32(self._first),
                    jnp.int32(self.num_starts),
                    batch_size=self.batch_size,
                    count=self.block,
                )
            )
        return self._draws[step - self._first]


# --- loss and step ----------------------------------------------------------------------------


def loss_fn(
    model: Dynamics, x: jax.Array, key: jax.Array, kl_weight: float
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Eq. 3 + kl_weight * Eq. 4 on a batch x (B, T, K, 4) with best-of-S posterior samples.

    Eq. 4's KL enters as the release computes it: the per-dimension KL of
    `losses.kl_diag_gaussians` averaged over batch, time and the D_z latent dimensions (not summed
    over them). The metrics also hold `last_pose`, Eq. 3 of predicting x_t by x_{t-1} on the same
    batch (frames 2..T): the trivial baseline the reconstruction is compared with.
    """
    out = model(x, key)
    recon = losses.vrnn_reconstruction(x, out.keypoints)
    per_dimension = losses.kl_diag_gaussians(
        out.mean_q, out.std_q, out.mean_p, out.std_p, axis=None
    )  # (B, T, D_z)
    kl = jnp.mean(per_dimension)
    total = recon + kl_weight * kl
    last_pose = jax.lax.stop_gradient(losses.vrnn_reconstruction(x[:, 1:], x[:, :-1]))
    return total, {"loss": total, "recon": recon, "kl": kl, "last_pose": last_pose}


@dataclasses.dataclass(frozen=True)
class StepSettings:
    """What the compiled step depends on besides the graph (hashable: a static jit argument)."""

    batch_size: int
    frames: int
    kl_weight: float
    optimizer: optim.OptimizerSettings

    @classmethod
    def of(cls, cfg: DynTrainConfig) -> StepSettings:
        return cls(
            cfg.data.batch_size, cfg.data.frames, cfg.kl_weight, optim.OptimizerSettings.of(cfg)
        )


@functools.partial(
    jax.jit, static_argnames=("graphdef", "settings", "mesh"), donate_argnames="state"
)
def train_step(state, x, base_key, step, *, graphdef, settings: StepSettings, mesh):
    """One data-parallel optimizer step of Eq. 3 + kl_weight * Eq. 4.

    The batch is sharded over the mesh's "data" axis, so each device runs the model on
    B / devices crops; the state and the metrics stay replicated.

    Args:
      state: {"model": nnx.State of the model, "opt": optax state of its nnx.Param} (donated).
      x: (B, T, K, 4) the crops this step drew (`CropDraws.at(step)`).
      base_key: the run's key; the step's model noise is the second half of
        split(fold_in(base_key, step)) (the first drew the crops), so it depends on nothing but
        its arguments (exact resume).
      step: int32 scalar, the number of steps already taken.
      graphdef: the model's nnx.GraphDef (static; equal for equal configurations, so a new run of
        the same configuration reuses the compiled step).
      settings: StepSettings (static).
      mesh: the data mesh (static, `parallel.data_mesh`).

    Returns:
      (new state, metrics dict of scalars).
    """
    model = nnx.merge(graphdef, state["model"])
    _, key_model = jax.random.split(jax.random.fold_in(base_key, step))
    x = parallel.constrain_batch(x, mesh)
    grad_fn = nnx.value_and_grad(loss_fn, has_aux=True)
    (_, metrics), grads = grad_fn(model, x, key_model, settings.kl_weight)
    state = optim.apply_gradients(model, grads, state, settings.optimizer)
    metrics["grad_norm"] = optax.tree.norm(grads)
    return parallel.constrain_replicated((state, metrics), mesh)


def make_train_step(
    graphdef: nnx.GraphDef, cfg: DynTrainConfig, mesh: jax.sharding.Mesh | None = None
) -> Callable[..., Any]:
    """`train_step` bound to a model, configuration and mesh (default: all devices):
    `(state, x, key, step)`."""
    mesh = parallel.data_mesh() if mesh is None else mesh
    return functools.partial(
        train_step, graphdef=graphdef, settings=StepSettings.of(cfg), mesh=mesh
    )


def build(
    cfg: DynTrainConfig, parents: tuple[int, ...], order: tuple[int, ...]
) -> tuple[nnx.GraphDef, dict[str, Any]]:
    """The model of `cfg` and its optimizer state: (graphdef, {"model": ..., "opt": ...})."""
    model = trained.build_dynamics(cfg, parents, order)
    return optim.init_state(model, StepSettings.of(cfg).optimizer)


# The fields the model's weights' shapes follow, besides the number of keypoints K: a run that
# starts from another run's weights (`init_from`) must have the same.
INIT_FIELDS = ("model.model", "model.latent", "model.hidden", "model.mlp")


def initial_weights(cfg: DynTrainConfig, num_keypoints: int) -> nnx.State:
    """The weights a fine-tuning run of `cfg` on a skeleton of `num_keypoints` keypoints starts
    from: the trained model of the phase-2 run `cfg.init_from` (`trained.restore_model`).

    Raises:
      FileNotFoundError, ValueError: one line; the source is no phase-2 run with a checkpoint,
        its network differs from `cfg`'s (`checkpoints.init_source_config`), or it models another K.
    """
    source = checkpoints.init_source_config(cfg, INIT_FIELDS, "phase-2")
    if not source.skel_run:
        raise ValueError(f"--init-from {cfg.init_from}: its config.json names no skel_run")
    tree = run_folder.read_skeleton(source.skel_run)
    if tree.num_keypoints != num_keypoints:
        raise ValueError(
            f"--init-from {cfg.init_from}: its model moves K={tree.num_keypoints} keypoints (the "
            f"skeleton of {source.skel_run}), the phase-1 run {cfg.skel_run} has K="
            f"{num_keypoints}; train on a phase-1 run of K={tree.num_keypoints} (--skel-run)"
        )
    return nnx.state(trained.restore_model(cfg.init_from, source, tree.parents, tree.order))


# --- validation -------------------------------------------------------------------------------


def evaluate(
    model: Dynamics, x: jax.Array, x_cond: jax.Array, key: jax.Array
) -> tuple[dict[str, jax.Array], jax.Array]:
    """Validation errors on crops x (V, T, K, 4), each next to a trivial baseline.

    - recon: posterior reconstruction (one sample, no best-of-S), frames 2..T;
      recon_best: the same with the training rule, best of S samples per step;
      last_pose: predicting x_t by x_{t-1} on the same frames.
    - gen: the T_cond = T/4 conditioning frames x_cond inferred with best-of-S posterior samples
      (as generation does), then a prior rollout; error on the generated frames against x;
      gen_hold: holding the last conditioning pose over the same frames.

    Args:
      x: (V, T, K, 4) validation crops.
      x_cond: (V, T_cond, K, 4) their conditioning keypoints: x[:, :T_cond] on the "sequence"
        route, the crop's first T_cond frames detected on their own on the "crop" route.
      key: PRNG key.

    Returns:
      (metrics, generated keypoints (V, T, K, 4): T_cond observed then generated frames).
    """
    key_rec, key_best, key_gen = jax.random.split(key, 3)
    recon, _ = model.reconstruct(x, key_rec, samples=1)
    recon_best, _ = model.reconstruct(x, key_best, samples=model.samples)
    t_cond = x_cond.shape[1]
    generated, _ = model.generate(x_cond, x.shape[1] - t_cond, key_gen)
    future = x[:, t_cond:]
    hold = jnp.broadcast_to(x_cond[:, -1:], future.shape)
    error = losses.vrnn_reconstruction  # Eq. 3's per-frame error, as in training
    metrics = {
        "recon": error(x[:, 1:], recon[:, 1:]),
        "recon_best": error(x[:, 1:], recon_best[:, 1:]),
        "last_pose": error(x[:, 1:], x[:, :-1]),
        "gen": error(future, generated[:, t_cond:]),
        "gen_hold": error(future, hold),
    }
    return metrics, generated


@functools.partial(jax.jit, static_argnames="graphdef")
def eval_step(state, x, x_cond, key, *, graphdef):
    """Compiled `evaluate`: (metrics, generated keypoints (T, K, 4) of the first crop)."""
    metrics, generated = evaluate(nnx.merge(graphdef, state["model"]), x, x_cond, key)
    return metrics, generated[0]


# --- loop -------------------------------------------------------------------------------------


def check_config(cfg: DynTrainConfig) -> None:
    """Refuses (ValueError naming the field) a configuration that cannot train, before compiling."""
    loop.check_positive({"data.batch_size": cfg.data.batch_size, "data.frames": cfg.data.frames})
    loop.check_loop(cfg.loop)
    optim.check_schedule(cfg.optim, cfg.loop)
    if cfg.data.inputs not in DYN_INPUTS:
        raise ValueError(
            f"data.inputs = {cfg.data.inputs!r} is not a phase-2 input; valid inputs: "
            f"{', '.join(DYN_INPUTS)}"
        )


def train_dynamics(
    cfg: DynTrainConfig,
    *,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = True,
    step_hook: Callable[[int, Any], Any] | None = None,
) -> loop.TrainSummary:
    """Phase 2's entry: trains the dynamics model on the phase-1 run `cfg.skel_run` (default: the
    latest of `cfg.data.name`) into the run folder `cfg.run` until `cfg.loop.steps`.

    The run folder is `cfg.run`, else a new one under the run root
    (`run_folder.config_run_dir`); the epochs count the training sequences
    (`config.resolve_epochs`), as `skel.train_skeleton` counts its own. The resolved phase-1
    folder is stored in config.json, so later tasks rebuild the model from the run folder alone.
    The skeleton and, by `cfg.data.inputs`, the detector or the exported keypoints are read and
    checked (`dyn_inputs.phase2_inputs`) before the run folder is made; the inputs are built
    once it is accepted.

    Args:
      cfg: the configuration.
      resume: continue the run folder from its latest checkpoint; its config.json may differ
        from `cfg` only in `run_folder.RESUMABLE_FIELDS`. Without it a run with `cfg.init_from`
        starts from that run's weights (`initial_weights`) and a fresh optimizer.
      overwrite: replace a run folder that holds files (refused without it or `resume`).
      progress: show a tqdm bar.
      step_hook: test hook `(step, state) -> state` applied before each step.

    Raises:
      NonFiniteLossError: the loss became NaN/inf (the last good checkpoint is kept).
    """
    check_config(cfg)
    skel_run = run_folder.find_skel_run(cfg.data.name, cfg.skel_run)
    tree = run_folder.read_skeleton(skel_run)
    parents, order = tree.parents, tree.order
    cfg = dataclasses.replace(cfg, skel_run=str(skel_run))
    train_sequences, inputs = dyn_inputs.phase2_inputs(cfg, skel_run, tree.num_keypoints)
    cfg = resolve_epochs(cfg, train_sequences, cfg.data.batch_size)
    mesh = parallel.data_mesh()
    parallel.check_batch_size(cfg.data.batch_size, "data.batch_size", mesh, "--batch-size ")
    run_dir = run_folder.config_run_dir(cfg.run, "dyn", cfg.data.name, cfg.model.model)
    graphdef, state = build(cfg, parents, order)
    if cfg.init_from and not resume:  # checked before the run folder is made
        initial = initial_weights(cfg, len(parents))
        state["model"] = checkpoints.checked_weights(initial, state["model"], cfg.init_from)
    run_dir = parallel.prepare_run_dir(run_dir, resume=resume, config=cfg, overwrite=overwrite)
    data = inputs()

    # Every host draws the same crops and holds the validation set: replicated global arrays.
    val_x, val_cond, base_key, val_key = parallel.replicate(
        (data.val, data.val_cond, jax.random.key(cfg.seed), jax.random.key(cfg.seed + 1)), mesh
    )
    draws = CropDraws(jax.random.key(cfg.seed), data.crops.num_starts, cfg.data.batch_size)
    state = parallel.replicate(state, mesh)
    step_fn = make_train_step(graphdef, cfg, mesh)

    def train_step(state: Any, step: int) -> tuple[Any, dict[str, jax.Array]]:
        x = parallel.global_array(data.crops.batch(draws.at(step)), mesh)
        return step_fn(state, x, base_key, np.int32(step))

    def validate(step: int, state: Any) -> dict[str, float]:
        metrics, generated = eval_step(state, val_x, val_cond, val_key, graphdef=graphdef)
        if parallel.is_primary():
            from nmjax import viz  # only the validating process draws

            viz.plot_motion(
                run_dir / run_folder.FIGURES_DIR / f"motion_{step:07d}.png",
                np.asarray(val_x[0]),
                np.asarray(generated),
                parents,
                val_cond.shape[1],
            )
        return {f"val/{k}": float(v) for k, v in metrics.items()}

    end = loop.train_loop(
        state,
        run_dir,
        resume=resume,
        loop=cfg.loop,
        train_step=train_step,
        validate=validate,
        progress=progress,
        desc="train-dyn",
        step_hook=step_hook,
        postfix=getattr(data.crops, "postfix", None),
    )
    return loop.TrainSummary.of(run_dir, end, cfg.loop)
