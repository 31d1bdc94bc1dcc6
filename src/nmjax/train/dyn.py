"""Phase 2: train the dynamics module (VRNN) on the keypoint trajectories of a phase-1 run.

`nmjax train-dyn [--data NAME] [--skel-run DIR] [--model nm|vrnn] [--preset default|cpu|tiny]
[--steps N] [--run DIR] [--resume]`.

Inputs (contract C10) come from a phase-1 run folder: `skeleton.json` (parents, root, order) and
`keypoints_{train,test}.npz` (one (T_seq,K,4) trajectory per sequence, written by the frozen
detector). Training crops of T frames are drawn inside the compiled step from all valid start
frames with the key fold_in(seed key, step), so a resumed run sees exactly the batches of an
uninterrupted one without saving a data-iterator state.

Loss: Eq. 3 (`losses.vrnn_reconstruction`) + kl_weight * Eq. 4 (`losses.kl_diag_gaussians`
summed over the latent, averaged over batch and time).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from nmjax import io, losses
from nmjax.config import PRESETS, DynTrainConfig, add_override_argument, apply_overrides, dyn_preset
from nmjax.models.dynamics import MODELS, Dynamics
from nmjax.train import common, parallel

RUNS_ROOT = Path("runs")
MAX_VAL_CROPS = 64


# --- phase-1 inputs -------------------------------------------------------------------------


def find_skel_run(
    data: str, skel_run: str | Path | None = None, runs_root: Path = RUNS_ROOT
) -> Path:
    """The phase-1 run to train on: `skel_run`, or the latest `runs_root/skel-<data>-*` folder.

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


def read_skeleton(run: Path) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """(parents, order) from `<run>/skeleton.json` (contract C10).

    Raises:
      FileNotFoundError: the skeleton has not been extracted yet (names the command).
      ValueError: the file lacks `parents` / `order` or they do not describe a rooted tree.
    """
    path = Path(run) / "skeleton.json"
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} not found; extract the skeleton first with "
            f"`nmjax extract-skeleton --run {run}`"
        )
    try:
        meta = json.loads(path.read_text())
        parents = tuple(int(p) for p in meta["parents"])
        order = tuple(int(k) for k in meta["order"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
        raise ValueError(
            f"{path} must be JSON with integer lists 'parents' and 'order' ({err}); "
            f"re-run `nmjax extract-skeleton --run {run}`"
        ) from err
    k = len(parents)
    position = {joint: i for i, joint in enumerate(order)}
    valid = (
        sorted(order) == list(range(k))
        and parents[order[0]] == order[0]
        and all(0 <= parents[j] < k and position[parents[j]] < position[j] for j in order[1:])
    )
    if not valid:
        raise ValueError(
            f"{path}: parents {parents} with order {order} is not a tree listed root first; "
            f"re-run `nmjax extract-skeleton --run {run}`"
        )
    return parents, order


def load_trajectories(run: Path, split: str) -> dict[str, np.ndarray]:
    """Keypoint trajectories {sequence: (T_seq, K, 4) float32} from `<run>/keypoints_<split>.npz`.

    When the cache is missing, the frozen detector of the run writes it first
    (`nmjax.train.skel.export_keypoints`).
    """
    path = Path(run) / f"keypoints_{split}.npz"
    if not path.is_file():
        try:
            from nmjax.train.skel import export_keypoints
        except ImportError as err:
            raise FileNotFoundError(
                f"{path} not found and the phase-1 exporter cannot be imported ({err}); write it "
                f"with `nmjax.train.skel.export_keypoints('{run}', '{split}')`"
            ) from err
        print(f"[train-dyn] {path.name} missing: running the frozen detector of {run}")
        export_keypoints(run, split)
    return read_trajectories(path)


def read_trajectories(path: Path) -> dict[str, np.ndarray]:
    """{sequence: (T_seq, K, 4) float32} of a keypoints .npz (the layout of keypoints_*.npz)."""
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} not found; write it with `nmjax.train.skel.export_keypoints(...)`"
        )
    with np.load(path) as npz:
        trajectories = {name: np.asarray(npz[name], np.float32) for name in npz.files}
    if not trajectories:
        raise ValueError(f"{path} holds no sequences; re-export the keypoints")
    for name, x in trajectories.items():
        if x.ndim != 3 or x.shape[-1] != 4:
            raise ValueError(f"{path}[{name!r}] has shape {x.shape}; expected (T_seq, K, 4)")
    return trajectories


# --- crops ------------------------------------------------------------------------------------


def crop_table(trajectories: dict[str, np.ndarray], frames: int) -> tuple[np.ndarray, np.ndarray]:
    """All sequences concatenated along time, and every start frame of a crop of `frames`.

    Sequences shorter than `frames` are padded with their last frame (as in the phase-1 pipeline).

    Returns:
      poses (F, K, 4) float32 and starts (S,) int32; `poses[s:s + frames]` is a valid crop for
      every s in `starts`.
    """
    pieces, starts, offset = [], [], 0
    for name in sorted(trajectories):
        x = trajectories[name]
        if len(x) < frames:
            x = np.concatenate([x, np.repeat(x[-1:], frames - len(x), axis=0)])
        pieces.append(x)
        starts.append(offset + np.arange(len(x) - frames + 1))
        offset += len(x)
    return np.concatenate(pieces).astype(np.float32), np.concatenate(starts).astype(np.int32)


def sample_crops(
    poses: jax.Array, starts: jax.Array, key: jax.Array, batch_size: int, frames: int
) -> jax.Array:
    """A batch (B, T, K, 4) of crops with start frames drawn uniformly from `starts` (jittable)."""
    chosen = starts[jax.random.randint(key, (batch_size,), 0, starts.shape[0])]
    return poses[chosen[:, None] + jnp.arange(frames)]


def validation_crops(trajectories: dict[str, np.ndarray], frames: int) -> np.ndarray:
    """Deterministic validation crops (V, T, K, 4): non-overlapping windows, at most 64."""
    poses, starts = crop_table(trajectories, frames)
    starts = starts[:: max(frames, 1)]
    if len(starts) > MAX_VAL_CROPS:
        starts = starts[np.linspace(0, len(starts) - 1, MAX_VAL_CROPS).astype(int)]
    return poses[starts[:, None] + np.arange(frames)]


# --- loss and step ----------------------------------------------------------------------------


def loss_fn(
    model: Dynamics, x: jax.Array, key: jax.Array, kl_weight: float
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Eq. 3 + kl_weight * Eq. 4 on a batch x (B, T, K, 4) with best-of-S posterior samples.

    The metrics also hold `last_pose`, Eq. 3 of predicting x_t by x_{t-1} on the same batch
    (frames 2..T): the trivial baseline the reconstruction is compared with.
    """
    out = model(x, key)
    recon = losses.vrnn_reconstruction(x, out.keypoints)
    kl = jnp.mean(losses.kl_diag_gaussians(out.mean_q, out.std_q, out.mean_p, out.std_p))
    total = recon + kl_weight * kl
    last_pose = jax.lax.stop_gradient(frame_error(x[:, 1:], x[:, :-1]))
    return total, {"loss": total, "recon": recon, "kl": kl, "last_pose": last_pose}


@dataclasses.dataclass(frozen=True)
class StepSettings:
    """The hyperparameters a compiled step depends on (hashable: a static jit argument)."""

    batch_size: int
    frames: int
    kl_weight: float
    learning_rate: float
    clip_norm: float

    @classmethod
    def of(cls, cfg: DynTrainConfig) -> StepSettings:
        return cls(cfg.batch_size, cfg.frames, cfg.kl_weight, cfg.learning_rate, cfg.clip_norm)

    def optimizer(self) -> optax.GradientTransformation:
        """Clipping then Adam (`common.make_optimizer`), no learning-rate milestones."""
        return common.make_optimizer(self.learning_rate, (), (), self.clip_norm)


@functools.partial(
    jax.jit, static_argnames=("graphdef", "settings", "mesh"), donate_argnames="state"
)
def train_step(state, poses, starts, base_key, step, *, graphdef, settings: StepSettings, mesh):
    """One data-parallel optimizer step of Eq. 3 + kl_weight * Eq. 4.

    The crops are gathered from the (replicated) table inside the step and sharded over the
    mesh's "data" axis, so each device runs the model on B / devices crops; the state and the
    metrics stay replicated.

    Args:
      state: {"model": nnx.State of the model, "opt": optax state of its nnx.Param} (donated).
      poses, starts: the crop table of `crop_table`.
      base_key: the run's key; the step uses fold_in(base_key, step) for its batch and noise, so
        it depends on nothing but its arguments (exact resume).
      step: int32 scalar, the number of steps already taken.
      graphdef: the model's nnx.GraphDef (static; equal for equal configurations, so a new run of
        the same configuration reuses the compiled step).
      settings: StepSettings (static).
      mesh: the data mesh (static, `parallel.data_mesh`).

    Returns:
      (new state, metrics dict of scalars).
    """
    model = nnx.merge(graphdef, state["model"])
    key_data, key_model = jax.random.split(jax.random.fold_in(base_key, step))
    x = sample_crops(poses, starts, key_data, settings.batch_size, settings.frames)
    x = parallel.constrain_batch(x, mesh)
    grad_fn = nnx.value_and_grad(loss_fn, has_aux=True)
    (_, metrics), grads = grad_fn(model, x, key_model, settings.kl_weight)
    params = nnx.state(model, nnx.Param)
    updates, opt = settings.optimizer().update(grads, state["opt"], params)
    nnx.update(model, optax.apply_updates(params, updates))
    metrics["grad_norm"] = optax.tree.norm(grads)
    return parallel.constrain_replicated(({"model": nnx.state(model), "opt": opt}, metrics), mesh)


def make_train_step(
    graphdef: nnx.GraphDef, cfg: DynTrainConfig, mesh: jax.sharding.Mesh | None = None
) -> Callable[..., Any]:
    """`train_step` bound to a model, configuration and mesh (default: all devices):
    `(state, poses, starts, key, step)`."""
    mesh = parallel.data_mesh() if mesh is None else mesh
    return functools.partial(
        train_step, graphdef=graphdef, settings=StepSettings.of(cfg), mesh=mesh
    )


def build(
    cfg: DynTrainConfig, parents: tuple[int, ...], order: tuple[int, ...]
) -> tuple[nnx.GraphDef, dict[str, Any]]:
    """The model of `cfg` and its optimizer state: (graphdef, {"model": ..., "opt": ...})."""
    model = Dynamics(cfg.model, parents, order, rngs=nnx.Rngs(cfg.seed))
    graphdef, model_state = nnx.split(model)
    opt = StepSettings.of(cfg).optimizer().init(nnx.state(model, nnx.Param))
    return graphdef, {"model": model_state, "opt": opt}


# --- validation -------------------------------------------------------------------------------


def frame_error(x: jax.Array, x_hat: jax.Array) -> jax.Array:
    """Eq. 3's per-frame error ||x_t - x_hat_t||^2, averaged over all leading axes."""
    return jnp.mean(jnp.sum(jnp.square(x - x_hat), axis=(-2, -1)))


def condition_frames(frames: int) -> int:
    """T_cond used in validation generation: a quarter of the crop, at least one frame."""
    return max(1, frames // 4)


def evaluate(
    model: Dynamics, x: jax.Array, key: jax.Array
) -> tuple[dict[str, jax.Array], jax.Array]:
    """Validation errors on crops x (V, T, K, 4), each next to a trivial baseline.

    - recon: posterior reconstruction (one sample, no best-of-S), frames 2..T;
      recon_best: the same with the training rule, best of S samples per step;
      last_pose: predicting x_t by x_{t-1} on the same frames.
    - gen: prior rollout after T_cond = T/4 observed frames, error on the generated frames;
      gen_hold: holding the last observed pose over the same frames.

    Returns:
      (metrics, generated keypoints (V, T, K, 4): T_cond observed then generated frames).
    """
    key_rec, key_best, key_gen = jax.random.split(key, 3)
    recon, _ = model.reconstruct(x, key_rec, samples=1)
    recon_best, _ = model.reconstruct(x, key_best, samples=model.samples)
    t_cond = condition_frames(x.shape[1])
    generated, _ = model.generate(x[:, :t_cond], x.shape[1] - t_cond, key_gen)
    future = x[:, t_cond:]
    hold = jnp.broadcast_to(x[:, t_cond - 1 : t_cond], future.shape)
    metrics = {
        "recon": frame_error(x[:, 1:], recon[:, 1:]),
        "recon_best": frame_error(x[:, 1:], recon_best[:, 1:]),
        "last_pose": frame_error(x[:, 1:], x[:, :-1]),
        "gen": frame_error(future, generated[:, t_cond:]),
        "gen_hold": frame_error(future, hold),
    }
    return metrics, generated


@functools.partial(jax.jit, static_argnames="graphdef")
def eval_step(state, x, key, *, graphdef):
    """Compiled `evaluate`: (metrics, generated keypoints (T, K, 4) of the first crop)."""
    metrics, generated = evaluate(nnx.merge(graphdef, state["model"]), x, key)
    return metrics, generated[0]


def plot_motion(
    path: Path,
    observed: np.ndarray,
    generated: np.ndarray,
    parents: tuple[int, ...],
    t_cond: int,
    columns: int = 6,
) -> None:
    """Observed (top) and generated (bottom) skeletons, x-y projection, at `columns` frames.

    Args:
      path: PNG file, written atomically.
      observed, generated: (T, K, 4) keypoints.
      parents: (K,) the skeleton.
      t_cond: frames given to the model; the frames after it are generated.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames = np.unique(np.linspace(0, len(observed) - 1, columns).astype(int))
    fig, axes = plt.subplots(2, len(frames), figsize=(2.2 * len(frames), 4.6), squeeze=False)
    both = np.concatenate([observed[..., :2], generated[..., :2]]).reshape(-1, 2)
    lo, hi = both.min(0) - 0.1, both.max(0) + 0.1
    for row, (label, x) in enumerate((("observed", observed), ("generated", generated))):
        for col, t in enumerate(frames):
            ax = axes[row, col]
            for k, p in enumerate(parents):
                if p != k:
                    ax.plot(x[t, [p, k], 0], x[t, [p, k], 1], "-", color="tab:blue", lw=1.5)
            alpha = np.clip(x[t, :, 3], 0, 1)  # intensity: dark = 0, yellow = 1
            ax.scatter(x[t, :, 0], x[t, :, 1], s=8, c=alpha, cmap="viridis", vmin=0, vmax=1)
            ax.set_xlim(lo[0], hi[0])
            ax.set_ylim(lo[1], hi[1])
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            kind = "cond" if t < t_cond else "gen"
            ax.set_title(f"{label} t={t}" + (f" ({kind})" if row else ""), fontsize=8)
    fig.tight_layout()
    with io.atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=80)
    plt.close(fig)


# --- loop -------------------------------------------------------------------------------------


def default_run_dir(cfg: DynTrainConfig) -> Path:
    return RUNS_ROOT / f"dyn-{cfg.data}-{cfg.model.model}-{time.strftime('%Y%m%d-%H%M%S')}"


def train(
    cfg: DynTrainConfig, *, resume: bool = False, progress: bool = True
) -> tuple[Path, list[dict[str, float]]]:
    """Trains `cfg` to `cfg.steps` steps; returns the run folder and the validation records.

    The resolved phase-1 folder is stored in the run's config.json (`skel_run`), so later tasks
    rebuild the model from the run folder alone.
    """
    from tqdm import tqdm

    skel_dir = find_skel_run(cfg.data, cfg.skel_run)
    parents, order = read_skeleton(skel_dir)
    train_traj = load_trajectories(skel_dir, "train")
    test_traj = load_trajectories(skel_dir, "test")
    for split, traj in (("train", train_traj), ("test", test_traj)):
        k = {x.shape[1] for x in traj.values()}
        if k != {len(parents)}:
            raise ValueError(
                f"{skel_dir}/keypoints_{split}.npz has K={sorted(k)} keypoints but skeleton.json "
                f"has {len(parents)} joints; re-export the keypoints of {skel_dir}"
            )
    cfg = dataclasses.replace(cfg, skel_run=str(skel_dir))
    mesh = parallel.data_mesh()
    parallel.check_batch_size(cfg.batch_size, "batch_size", mesh, "--batch-size ")
    run_dir = Path(cfg.run) if cfg.run is not None else default_run_dir(cfg)
    run_dir = parallel.prepare_run_dir(run_dir, resume=resume, config=cfg)

    # Every host holds the whole crop table and validation set: replicated global arrays.
    poses, starts, val_x, base_key, val_key = parallel.replicate(
        (
            *crop_table(train_traj, cfg.frames),
            validation_crops(test_traj, cfg.frames),
            jax.random.key(cfg.seed),
            jax.random.key(cfg.seed + 1),
        ),
        mesh,
    )
    graphdef, state = build(cfg, parents, order)
    state = parallel.replicate(state, mesh)
    step_fn = make_train_step(graphdef, cfg, mesh)

    checkpointer = common.Checkpointer(run_dir / "checkpoints", keep=cfg.keep_checkpoints)
    step = 0
    if resume and checkpointer.latest_step() is not None:
        step, state = checkpointer.restore(state)
    writer = parallel.metric_writer(run_dir, resume_step=step if resume else None)
    history: list[dict[str, float]] = []

    def validate(step: int) -> None:
        metrics, generated = eval_step(state, val_x, val_key, graphdef=graphdef)
        scalars = {f"val/{k}": float(v) for k, v in metrics.items()}
        writer.write_scalars(step, scalars)
        history.append({"step": step, **scalars})
        if not parallel.is_primary():
            return
        plot_motion(
            run_dir / "figures" / f"motion_{step:07d}.png",
            np.asarray(val_x[0]),
            np.asarray(generated),
            parents,
            condition_frames(cfg.frames),
        )
        pbar.write(
            f"step {step}: val recon {scalars['val/recon']:.4g} (best of S "
            f"{scalars['val/recon_best']:.4g}; last pose "
            f"{scalars['val/last_pose']:.4g}), gen {scalars['val/gen']:.4g} (hold "
            f"{scalars['val/gen_hold']:.4g})"
        )

    pbar = tqdm(total=cfg.steps, initial=step, disable=not progress, desc="train-dyn")
    tic, tic_step = time.perf_counter(), step
    try:
        while step < cfg.steps:
            state, metrics = step_fn(state, poses, starts, base_key, np.int32(step))
            step += 1
            pbar.update(1)
            if step % cfg.log_every == 0 or step == cfg.steps:
                scalars = {f"train/{k}": float(v) for k, v in metrics.items()}
                toc = time.perf_counter()
                scalars["train/steps_per_s"] = (step - tic_step) / max(toc - tic, 1e-9)
                tic, tic_step = toc, step
                writer.write_scalars(step, scalars)
                pbar.set_postfix(loss=f"{scalars['train/loss']:.4g}")
            if step % cfg.val_every == 0 or step == cfg.steps:
                validate(step)
            if step % cfg.ckpt_every == 0 or step == cfg.steps:
                if step not in checkpointer.all_steps():
                    checkpointer.save(step, state)
    finally:
        pbar.close()
        checkpointer.close()
        writer.close()
    return run_dir, history


def restore_model(run_dir: str | Path, step: int | None = None) -> Dynamics:
    """The trained dynamics model of a phase-2 run folder (latest checkpoint by default)."""
    run_dir = Path(run_dir)
    cfg = common.load_config(run_dir, DynTrainConfig)
    parents, order = read_skeleton(Path(cfg.skel_run))
    graphdef, abstract = nnx.eval_shape(lambda: build(cfg, parents, order))
    with common.Checkpointer(run_dir / "checkpoints", keep=cfg.keep_checkpoints) as ckpt:
        _, state = ckpt.restore(abstract, step=step)
    return nnx.merge(graphdef, state["model"])


# --- command ----------------------------------------------------------------------------------


def parse_args(argv: list[str]) -> tuple[DynTrainConfig, bool]:
    parser = argparse.ArgumentParser(
        prog="nmjax train-dyn", description="Phase 2: train the VRNN dynamics on a phase-1 run."
    )
    parser.add_argument("--data", default="synth-hand", help="dataset name (default synth-hand)")
    parser.add_argument("--skel-run", default=None, help="phase-1 run (default: latest of DATA)")
    parser.add_argument("--model", default="nm", choices=MODELS, help="nm (FK) or vrnn baseline")
    parser.add_argument("--preset", default="default", choices=PRESETS)
    parser.add_argument("--steps", type=int, default=None, help="override the preset's steps")
    parser.add_argument("--run", default=None, help="run folder (default runs/dyn-<data>-...)")
    parser.add_argument("--resume", action="store_true", help="continue the run in --run")
    parser.add_argument("--seed", type=int, default=None)
    parser.add_argument(
        "--batch-size", type=int, default=None, help="global batch (a multiple of the devices)"
    )
    add_override_argument(
        parser, "override any config field, e.g. --set kl_weight=1e-4 --set model.hidden=256"
    )
    parallel.add_distributed_args(parser)
    args = parser.parse_args(argv)
    if args.resume and args.run is None:
        parser.error("--resume needs --run DIR (the run folder to continue)")
    cfg = dyn_preset(args.data, args.preset)
    cfg = dataclasses.replace(
        cfg,
        skel_run=args.skel_run,
        model=dataclasses.replace(cfg.model, model=args.model),
        run=args.run,
    )
    if args.steps is not None:
        if args.steps < 1:
            parser.error(f"--steps must be >= 1, got {args.steps}")
        cfg = dataclasses.replace(cfg, steps=args.steps)
    if args.seed is not None:
        cfg = dataclasses.replace(cfg, seed=args.seed)
    if args.batch_size is not None:
        if args.batch_size < 1:
            parser.error(f"--batch-size must be >= 1, got {args.batch_size}")
        cfg = dataclasses.replace(cfg, batch_size=args.batch_size)
    try:
        cfg = apply_overrides(cfg, args.overrides)
    except ValueError as err:
        parser.error(str(err))
    return cfg, args.resume


def main(argv: list[str]) -> int:
    cfg, resume = parse_args(argv)
    try:
        parallel.initialize_from_argv(argv)
        if resume:
            # The run's own configuration decides the model; --steps may extend it.
            saved = common.load_config(cfg.run, DynTrainConfig)
            steps = cfg.steps if "--steps" in argv else saved.steps
            cfg = dataclasses.replace(saved, steps=steps)
        run_dir, history = train(cfg, resume=resume)
    except (FileNotFoundError, ValueError) as err:
        print(f"nmjax train-dyn: {err}", file=sys.stderr)
        return 1
    last = history[-1] if history else {}
    print(f"run folder: {run_dir}; final validation: {json.dumps(last)}")
    return 0
