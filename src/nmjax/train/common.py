"""Pieces shared by both trainers: the training loop, optimizer, run folders, orbax checkpoints,
metric logging, resume rules.

A training state is the pytree `nnx.state((model, optimizer))` of a model and its
`nnx.Optimizer`, split once with `nnx.split`; each phase jits one module-level step over that
pytree (graphdef and settings static, state donated), and `train_loop` drives it: it opens the
run's checkpoints and metric log, restores a resumed run, hands the state to `Checkpointer`
unchanged and logs what the step returns.

The names of every file of a run folder are here, beside the trainers that write them;
`nmjax.runs` reads them by the same names (contract C10).
"""

from __future__ import annotations

import dataclasses
import gc
import json
import math
import shutil
import time
import types
import typing
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import grain
import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
from flax import nnx
from orbax.checkpoint import checkpoint_managers as ocp_policies

from nmjax import atomic
from nmjax.config import OPTIMIZER_RESETS

# --- the run folder (contract C10) --------------------------------------------------------------

# Both phases: written when the run starts and as it trains.
CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.jsonl"
TENSORBOARD_DIR = "tb"
CHECKPOINTS = "checkpoints"
FIGURES_DIR = "figures"
# Phase 1: the inputs of skeleton extraction, written when training ends (`train.skel`) ...
AFFINITY_FILE = "affinity.npy"
STATS_FILE = "keypoint_stats.npz"
STATS_KEYS = ("intensities", "rest_positions", "example_voxels", "example_keypoints")
# ... and what `nmjax.runs` adds after it: the skeleton and each split's keypoints.
SKELETON_FILE = "skeleton.json"


def keypoints_file(run: str | Path, split: str) -> Path:
    """`<run>/keypoints_<split>.npz`: the frozen detector's keypoints of every sequence."""
    return Path(run) / f"keypoints_{split}.npz"


# Fields a resumed run may change: how long it trains and what it reports, not what it computes.
RESUMABLE_FIELDS = frozenset(
    {"steps", "log_every", "val_every", "ckpt_every", "time_limit_minutes", "run", "data.root"}
)


class NonFiniteLossError(RuntimeError):
    """The training loss became NaN or infinite."""


def check_positive(cfg: Any, names: tuple[str, ...]) -> None:
    """Raises ValueError naming the first field of `names` in `cfg` that is below 1."""
    for name in names:
        if getattr(cfg, name) < 1:
            raise ValueError(f"{name} must be >= 1, got {getattr(cfg, name)}")


def check_schedule(cfg: Any) -> None:
    """Refuses (ValueError naming the field) a schedule that cannot run: no length, decays that
    do not fit it, an unknown optimizer_reset. Phase 1 and phase 2 share it."""
    if cfg.optimizer_reset not in OPTIMIZER_RESETS:
        raise ValueError(
            f"optimizer_reset must be one of {', '.join(OPTIMIZER_RESETS)}, got "
            f"{cfg.optimizer_reset!r}"
        )
    if cfg.epochs < 0:
        raise ValueError(f"epochs must be >= 0 (0: a step count instead), got {cfg.epochs}")
    if cfg.epochs == 0 and cfg.steps < 1:
        raise ValueError(f"steps must be >= 1 when epochs = 0, got {cfg.steps}")
    decays = getattr(cfg, "decay_epochs", ())
    if cfg.epochs > 0 and any(not 0 < e < cfg.epochs for e in decays):
        raise ValueError(f"decay_epochs {decays} must lie inside the run's {cfg.epochs} epochs")


class RestartState(NamedTuple):
    """State of `restart_every`: the wrapped transformation's state and the updates counted."""

    inner: Any
    count: jax.Array


def restart_every(inner: optax.GradientTransformation, period: int) -> optax.GradientTransformation:
    """`inner` with its state created anew before every `period`-th update (updates period,
    2 period, ...; never for period 0, which keeps the state's layout for a run whose epochs are
    not counted yet): as if the optimizer were built afresh at each epoch boundary, which is how
    the release trains (a new `torch.optim.Adam` every epoch: moments and bias correction start
    over). Inside a compiled step the choice is a `jnp.where` over the state, so the step is
    compiled once and a resumed run restarts at the same updates as a straight one.

    `inner.init` is called on the updates, which have the parameters' structure and shapes.
    """
    if period < 0:
        raise ValueError(f"restart_every: period must be >= 0 (0: never), got {period}")

    def init(params):
        return RestartState(inner.init(params), jnp.zeros([], jnp.int32))

    def update(updates, state, params=None):
        restart = (state.count > 0) & (state.count % max(period, 1) == 0) & (period > 0)
        fresh = inner.init(updates)
        inner_state = jax.tree.map(lambda f, o: jnp.where(restart, f, o), fresh, state.inner)
        updates, inner_state = inner.update(updates, inner_state, params)
        return updates, RestartState(inner_state, state.count + 1)

    return optax.GradientTransformation(init, update)


def make_optimizer(
    learning_rate: float,
    milestones: tuple[int, ...] = (),
    decay: tuple[float, ...] = (),
    clip_norm: float | None = None,
    restart_period: int | None = None,
) -> optax.GradientTransformation:
    """Optional clipping by global norm, then Adam with a piecewise-constant learning rate.

    The rate is `learning_rate` until `milestones[0]`, `learning_rate * decay[0]` until
    `milestones[1]`, then `learning_rate * decay[1]` (the release: decay [0.25, 0.1]; each factor
    is relative to the initial rate, not compounded). The rate follows the run's step count;
    with `restart_period`, Adam's own state (moments, bias-correction count) restarts every that
    many steps (`restart_every`).

    Args:
      learning_rate: initial Adam step size.
      milestones: increasing optimizer steps at which the rate changes.
      decay: factor of the initial rate from each milestone on; same length as `milestones`.
      clip_norm: maximum global gradient norm; None or <= 0 disables clipping.
      restart_period: steps per epoch when Adam restarts each epoch (0: not counted yet, the
        state laid out for it but never restarted); None: one Adam state for the run.

    Returns:
      An optax transformation.
    """
    milestones, decay = tuple(int(m) for m in milestones), tuple(float(d) for d in decay)
    if len(milestones) != len(decay):
        raise ValueError(
            f"lr_milestones {milestones} and lr_decay {decay} must have the same length"
        )
    if any(b <= a for a, b in zip(milestones, milestones[1:], strict=False)):
        raise ValueError(f"lr_milestones {milestones} must be strictly increasing")
    if learning_rate <= 0 or any(d <= 0 for d in decay):
        raise ValueError(
            f"learning_rate {learning_rate} and lr_decay {decay} must be positive numbers"
        )
    # optax compounds the scales; convert "factor of the initial rate" into step-to-step ratios.
    ratios = [d / p for d, p in zip(decay, (1.0, *decay)[:-1], strict=True)]
    schedule = optax.piecewise_constant_schedule(
        learning_rate, dict(zip(milestones, ratios, strict=True))
    )
    moments = optax.scale_by_adam()
    if restart_period is not None:
        moments = restart_every(moments, restart_period)
    parts = [moments, optax.scale_by_learning_rate(schedule)]
    if clip_norm is not None and clip_norm > 0:
        parts.insert(0, optax.clip_by_global_norm(clip_norm))
    return optax.chain(*parts)


@dataclasses.dataclass(frozen=True)
class OptimizerSettings:
    """The optimizer of `make_optimizer`, hashable: the compiled steps take it as a static
    argument and build the optax transformation inside the trace, so two runs of one
    configuration share one compiled step."""

    learning_rate: float
    milestones: tuple[int, ...] = ()
    decay: tuple[float, ...] = ()
    clip_norm: float | None = None
    ema_decay: float = 0.0  # > 0: keep an average of the weights (`ema_weights`); 0: none
    # Adam restarts every that many steps (`restart_every`; 0 until the epochs are counted);
    # None: one Adam state for the run.
    restart_period: int | None = None

    @classmethod
    def of(cls, cfg: Any) -> OptimizerSettings:
        """From a train config (phase 2 has no learning-rate milestones and no weight average).

        The epochs must be resolved (`config.resolve_epochs`) for the restarts and decays to be
        in it: a configuration that is not (a benchmark of the step) gets the decays that are
        already in steps and the restarting state's layout without restarts, so its checkpoints
        have the layout of the resolved run's.
        """
        milestones = tuple(getattr(cfg, "lr_milestones", ()))
        decay = tuple(getattr(cfg, "lr_decay", ()))[: len(milestones)]
        ema_decay = float(getattr(cfg, "ema_decay", 0.0))
        reset = getattr(cfg, "optimizer_reset", "never")
        period = cfg.steps_per_epoch if reset == "epoch" else None
        return cls(cfg.learning_rate, milestones, decay, cfg.clip_norm, ema_decay, period)

    def make(self) -> optax.GradientTransformation:
        return make_optimizer(
            self.learning_rate, self.milestones, self.decay, self.clip_norm, self.restart_period
        )

    def make_ema(self) -> optax.GradientTransformation:
        """The weight average: optax.ema over the parameters after each update (bias-corrected,
        so the first steps are not pulled towards the initialisation)."""
        return optax.ema(self.ema_decay, debias=True)


def init_state(model: Any, optimizer: OptimizerSettings) -> tuple[Any, dict[str, Any]]:
    """(graphdef, {"model": model state, "opt": optax state of its nnx.Param[, "ema": optax.ema
    state of the nnx.Param when `optimizer.ema_decay` > 0]}) of a new model."""
    graphdef, model_state = nnx.split(model)
    params = nnx.state(model, nnx.Param)
    state = {"model": model_state, "opt": optimizer.make().init(params)}
    if optimizer.ema_decay > 0:
        state["ema"] = optimizer.make_ema().init(params)
    return graphdef, state


def apply_gradients(
    model: Any, grads: Any, state: dict[str, Any], optimizer: OptimizerSettings
) -> dict[str, Any]:
    """Inside a step: one optimizer update of `model`'s nnx.Param, and of the weight average
    when `state` keeps one; the new {"model", "opt"[, "ema"]}."""
    params = nnx.state(model, nnx.Param)
    updates, opt_state = optimizer.make().update(grads, state["opt"], params)
    params = optax.apply_updates(params, updates)
    nnx.update(model, params)
    new_state = {"model": nnx.state(model), "opt": opt_state}
    if "ema" in state:
        _, new_state["ema"] = optimizer.make_ema().update(params, state["ema"])
    return new_state


def trained_model(graphdef: Any, state: dict[str, Any], ema_decay: float) -> Any:
    """The model that `state` stands for: its weights, or, when the run keeps a weight average
    ("ema", decay `ema_decay`), the bias-corrected running average of its nnx.Param (Polyak
    averaging with exponential weights), which validation and every exported model then use."""
    # A copy: merged without one, the model's variables are those of `state`, and putting the
    # average into them would overwrite the weights being trained.
    model = nnx.merge(graphdef, state["model"], copy=True)
    if "ema" in state:
        ema = state["ema"]
        nnx.update(model, optax.tree.bias_correction(ema.ema, ema_decay, ema.count))
    return model


def abstract_state(state: Any) -> Any:
    """Shapes, dtypes and shardings of `state`: a restore target that keeps its placement."""
    return jax.tree.map(
        lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=getattr(x, "sharding", None)),
        state,
    )


def pad_with_last(x: np.ndarray, length: int) -> np.ndarray:
    """`x` (N, ...) extended to at least `length` along axis 0 by repeating its last entry (a
    sequence's last frame, a batch's last crop); unchanged when it is long enough."""
    if len(x) >= length:
        return x
    return np.concatenate([x, np.repeat(x[-1:], length - len(x), axis=0)])


def config_to_dict(config: Any) -> dict[str, Any]:
    """`dataclasses.asdict`, with tuples turned into lists so that it round-trips through JSON."""
    return json.loads(json.dumps(dataclasses.asdict(config)))


def config_from_dict(cls: type, data: Mapping[str, Any], *, source: str = "config") -> Any:
    """Rebuilds the (nested, frozen) dataclass `cls` from `config_to_dict` output.

    Unknown keys are refused so that a stale config file is noticed; missing keys take the
    dataclass default.
    """
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(
            f"{source}: unknown field(s) {unknown} for {cls.__name__}; "
            f"valid fields: {sorted(names)}"
        )
    kwargs = {}
    for name, value in data.items():
        kwargs[name] = _convert(hints[name], value, source=f"{source}.{name}")
    return cls(**kwargs)


def _convert(hint: Any, value: Any, *, source: str) -> Any:
    if dataclasses.is_dataclass(hint) and isinstance(hint, type):
        if not isinstance(value, Mapping):
            raise ValueError(f"{source}: expected a mapping for {hint.__name__}, got {value!r}")
        return config_from_dict(hint, value, source=source)
    origin = typing.get_origin(hint)
    if origin is tuple and isinstance(value, list | tuple):
        return tuple(value)
    if origin in (typing.Union, types.UnionType) and isinstance(value, list):
        return tuple(value)
    return value


def check_run_dir(path: str | Path, *, resume: bool, config: Any, overwrite: bool = False) -> None:
    """Every refusal `prepare_run_dir` can make, without writing anything.

    With `resume` the folder must hold a config.json that `config` differs from only in
    `RESUMABLE_FIELDS`, and at least one complete checkpoint.

    Raises:
      FileNotFoundError: `resume` and the folder, its config.json or its checkpoints are missing.
      ValueError: the folder exists and holds files, and neither `resume` nor `overwrite` is set;
        or `resume` with a configuration that changes what the run computes, or of a folder
        whose only checkpoint is an import's step 0 (pointing to --init-from).
    """
    path = Path(path)
    if not resume:
        if path.exists() and (not path.is_dir() or any(path.iterdir())) and not overwrite:
            raise ValueError(
                f"run folder {path} already exists; pass --resume to continue it, --overwrite to "
                "replace it, or choose another --run"
            )
        return
    if not path.is_dir():
        raise FileNotFoundError(
            f"cannot resume: run folder {path} does not exist; drop --resume to start a new run"
        )
    check_resume_config(load_config(path, type(config)), config, path)
    steps = checkpoint_steps(path / CHECKPOINTS)
    if not steps:
        raise FileNotFoundError(
            f"cannot resume {path}: it has no complete checkpoint; start it again with "
            "--overwrite (or drop --resume with a new --run)"
        )
    if steps == [0]:
        # Only `nmjax import-release` writes a step 0: weights with an optimizer state that no
        # step has touched. Resuming would train the imported folder itself, in place.
        raise ValueError(
            f"cannot resume {path}: it holds imported weights (checkpoint 0) and no optimizer "
            f"state of a training run; fine-tune them in a new run with --init-from {path}"
        )


def init_source_config(config: Any, fields: tuple[str, ...], phase: str) -> Any:
    """The configuration of the run `config.init_from` that a new run starts from (fine-tuning),
    after refusing, in one line, a source that a run of `config` cannot take its weights from.

    Args:
      config: the new run's configuration (a `SkelTrainConfig` or `DynTrainConfig`).
      fields: dotted config fields that shape the network's weights: they must be equal.
      phase: "phase-1" or "phase-2", for the messages.

    Raises:
      FileNotFoundError: no run folder or no checkpoint there.
      ValueError: a run of the other phase, or a network that differs in `fields` (each named
        with both values and the `--set` that matches the source).
    """
    source = Path(config.init_from)
    if not (source / CONFIG_FILE).is_file():
        raise FileNotFoundError(
            f"--init-from {source}: no {CONFIG_FILE} there; give a {phase} run folder (one that "
            "`nmjax train-...` or `nmjax import-release` wrote)"
        )
    try:
        saved = load_config(source, type(config))
    except (ValueError, TypeError) as err:
        raise ValueError(f"--init-from {source} is not a {phase} run ({err})") from err
    if not checkpoint_steps(source / CHECKPOINTS):
        raise FileNotFoundError(f"--init-from {source}: the run has no complete checkpoint")
    old, new = _flatten(config_to_dict(saved)), _flatten(config_to_dict(config))
    differ = [name for name in fields if old.get(name) != new.get(name)]
    if differ:

        def option(value: Any) -> str:
            return ",".join(map(str, value)) if isinstance(value, list) else str(value)

        diffs = ", ".join(f"{k} (run: {old.get(k)!r}, asked: {new.get(k)!r})" for k in differ)
        sets = " ".join(f"--set {k}={option(old.get(k))}" for k in differ)
        raise ValueError(
            f"--init-from {source}: its network differs from this run's in {diffs}; start from "
            f"a run of the same network, or give this one its network: {sets}"
        )
    return saved


def checked_weights(weights: Any, expected: Any, source: str) -> Any:
    """`weights` (a model state restored from the run `source`) to start a new model whose own
    state is `expected`, after checking that every leaf has the expected shape and dtype.

    Raises:
      ValueError: a leaf missing, extra or of another shape (`_check_compatible`).
    """
    _check_compatible(expected, weights, f"--init-from {source}")
    return weights


def check_resume_config(saved: Any, config: Any, path: str | Path) -> None:
    """Refuses (ValueError naming the fields) a resume whose config changes more than
    `RESUMABLE_FIELDS` of the run's saved one."""
    old, new = _flatten(config_to_dict(saved)), _flatten(config_to_dict(config))
    changed = sorted(
        k for k in old.keys() | new.keys() if old.get(k) != new.get(k) and k not in RESUMABLE_FIELDS
    )
    if changed:
        diffs = ", ".join(f"{k} (run: {old.get(k)!r}, asked: {new.get(k)!r})" for k in changed)
        raise ValueError(
            f"--resume continues {path} with its own configuration, but the command changes "
            f"{diffs}; drop those options (only --steps and the log/val/checkpoint cadence may "
            "change) or start a new run with --run"
        )


def _flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, Mapping):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def checkpoint_steps(directory: str | Path) -> list[int]:
    """The complete checkpoint steps in `directory`, without creating or cleaning anything.

    Orbax writes a step into a temporary folder and renames it when the save is complete, so a
    process killed mid-save leaves only a `<step>.orbax-checkpoint-tmp-*` folder, which is not a
    step here (the next `Checkpointer` removes it).
    """
    directory = Path(directory)
    if not directory.is_dir():
        return []
    return sorted(int(p.name) for p in directory.iterdir() if p.is_dir() and p.name.isdigit())


def prepare_run_dir(
    path: str | Path, *, resume: bool, config: Any, overwrite: bool = False
) -> Path:
    """Creates (or reopens, with `resume`) a run folder and writes `config.json` into it.

    Nothing is written before every check of `check_run_dir` has passed.

    Args:
      path: the run folder.
      resume: continue an existing run; the folder must hold a checkpoint and a config that
        `config` changes only in `RESUMABLE_FIELDS`.
      config: a dataclass; `dataclasses.asdict(config)` is written to `<path>/config.json`.
      overwrite: delete an existing folder and start afresh (ignored with `resume`).

    Returns:
      The run folder as a Path.

    Raises:
      FileNotFoundError, ValueError: see `check_run_dir`.
    """
    path = Path(path)
    check_run_dir(path, resume=resume, config=config, overwrite=overwrite)
    if not resume and path.exists() and (not path.is_dir() or any(path.iterdir())):
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink()
    path.mkdir(parents=True, exist_ok=True)
    atomic.write_json(path / CONFIG_FILE, config_to_dict(config))
    return path


def load_config(run_dir: str | Path, cls: type) -> Any:
    """Reads `<run_dir>/config.json` back into the dataclass `cls`."""
    file = Path(run_dir) / CONFIG_FILE
    if not file.is_file():
        raise FileNotFoundError(f"{file} not found; is {run_dir} a run folder written by nmjax?")
    try:
        data = json.loads(file.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{file} is not valid JSON ({err}); the run folder is damaged") from err
    return config_from_dict(cls, data, source=str(file))


class Checkpointer:
    """One `ocp.CheckpointManager`: the last `keep` checkpoints plus the best by `best_metric`.

    Each checkpoint holds the item `state` (a pytree, normally `nnx.state((model, optimizer))`)
    and, when given, the item `data` (the grain iterator's position). Saves are synchronous so a
    checkpoint is complete on disk when `save` returns, before the next step donates the buffers.
    Existing checkpoints are never overwritten or deleted except by the retention policy.
    """

    def __init__(self, directory: str | Path, keep: int = 3, best_metric: str | None = None):
        if keep < 1:
            raise ValueError(f"keep_checkpoints must be >= 1, got {keep}")
        self.directory = Path(directory).absolute()
        self.best_metric = best_metric
        policies: list[Any] = [ocp_policies.LatestN(n=keep)]
        best_fn = None
        if best_metric is not None:

            def best_fn(metrics: Mapping[str, float]) -> float:
                return float(metrics.get(best_metric, math.inf))

            policies.append(
                ocp_policies.BestN(
                    get_metric_fn=best_fn,
                    reverse=True,  # sorted descending, the last (lowest) n are kept
                    n=1,
                    keep_checkpoints_without_metrics=False,
                )
            )
        options = ocp.CheckpointManagerOptions(
            # best_fn only makes orbax record metrics and answer best_step(); which checkpoints
            # survive is decided by the preservation policy alone.
            best_fn=best_fn,
            best_mode="min",
            preservation_policy=ocp_policies.AnyPreservationPolicy(policies),
            enable_async_checkpointing=False,
            create=True,
        )
        self._manager = ocp.CheckpointManager(
            self.directory,
            options=options,
            # Named handlers let a fresh process read a checkpoint's metadata before restoring.
            item_handlers={
                "state": ocp.StandardCheckpointHandler(),
                "data": grain.checkpoint.CheckpointHandler(),
            },
        )

    def latest_step(self) -> int | None:
        """The newest saved step, or None."""
        return self._manager.latest_step()

    def all_steps(self) -> list[int]:
        return sorted(self._manager.all_steps())

    def best_step(self) -> int | None:
        """The step with the lowest `best_metric` among kept checkpoints, or None."""
        return self._manager.best_step() if self.best_metric is not None else None

    def save(
        self,
        step: int,
        state: Any,
        metrics: Mapping[str, Any] | None = None,
        data_iter: grain.DatasetIterator | None = None,
    ) -> None:
        """Writes checkpoint `step`; refuses to overwrite an existing one."""
        if step in self._manager.all_steps():
            raise ValueError(
                f"checkpoint {step} already exists in {self.directory}; refusing to overwrite it"
            )
        items: dict[str, Any] = {"state": ocp.args.StandardSave(state)}
        if data_iter is not None:
            items["data"] = grain.checkpoint.CheckpointSave(data_iter)
        if metrics is not None:
            metrics = {k: float(v) for k, v in metrics.items()}
        self._manager.save(step, args=ocp.args.Composite(**items), metrics=metrics, force=True)

    def restore(
        self,
        abstract_state: Any,
        step: int | None = None,
        data_iter: grain.DatasetIterator | None = None,
    ) -> tuple[int, Any]:
        """Restores checkpoint `step` (default: the latest) into the structure of `abstract_state`.

        Args:
          abstract_state: pytree of `jax.ShapeDtypeStruct` (e.g. from `nnx.eval_shape`) or arrays.
          step: which checkpoint; None = the latest.
          data_iter: grain iterator whose position is restored in place, when given.

        Returns:
          (step, state).

        Raises:
          FileNotFoundError: there is no checkpoint (or not that step).
          ValueError: the checkpoint is corrupt or belongs to a different model/configuration.
        """
        steps = self.all_steps()
        if step is None:
            if not steps:
                raise FileNotFoundError(f"no checkpoint found in {self.directory}")
            step = steps[-1]
        elif step not in steps:
            raise FileNotFoundError(
                f"checkpoint {step} not found in {self.directory}; available steps: {steps}"
            )
        items: dict[str, Any] = {"state": ocp.args.StandardRestore(abstract_state)}
        if data_iter is not None:
            items["data"] = grain.checkpoint.CheckpointRestore(data_iter)
        where = f"checkpoint {step} in {self.directory}"
        failure = None
        try:
            # Refuse a mismatched checkpoint from its metadata, before any array read starts:
            # orbax abandons the in-flight reads of a failed restore to a closed event loop.
            saved = self._manager.item_metadata(step)["state"]
        except Exception as err:  # orbax/tensorstore raise many types for damaged files
            failure = err
        else:
            _check_compatible(abstract_state, saved, where)
            try:
                restored = self._manager.restore(step, args=ocp.args.Composite(**items))
            except Exception as err:
                failure = err
        if failure is not None:
            lines = str(failure).strip().splitlines()
            reason = f"{type(failure).__name__}: {lines[0][:300] if lines else ''}"
            # Finalise the read coroutines orbax abandoned on failure now, while the error is
            # reported, rather than at some later garbage collection.
            gc.collect()
            raise ValueError(
                f"{where} cannot be restored ({reason}). It is corrupt or was written by a "
                "different model configuration; it was left untouched. Start a new run "
                "(--run DIR) or resume from the matching configuration."
            )
        return step, restored["state"]

    def close(self) -> None:
        self._manager.wait_until_finished()
        self._manager.close()

    def __enter__(self) -> Checkpointer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _leaf_specs(tree: Any) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """{dotted leaf path: (shape, dtype)} for a pytree of arrays or orbax array metadata."""

    def name(path: tuple[Any, ...]) -> str:
        return ".".join(str(getattr(k, "key", getattr(k, "name", k))) for k in path)

    leaves = jax.tree_util.tree_leaves_with_path(tree)
    # nnx.Variable leaves end in `.value`; orbax metadata spells it as a dict key.
    return {
        name(path).removesuffix(".value"): (tuple(np.shape(x)), np.dtype(x.dtype))
        for path, x in leaves
    }


def _check_compatible(expected: Any, saved: Any, where: str) -> None:
    """Raises ValueError unless `saved` has the leaves, shapes and dtypes of `expected`."""
    want, have = _leaf_specs(expected), _leaf_specs(saved)
    if want.keys() != have.keys():
        missing = sorted(want.keys() - have.keys())[:3]
        extra = sorted(have.keys() - want.keys())[:3]
        raise ValueError(
            f"{where} has a different parameter structure than the current model (missing "
            f"{missing}, unexpected {extra}); it was written by another configuration (start a "
            "new run or use the run's own config)"
        )
    for key, (shape, dtype) in want.items():
        if have[key] != (shape, dtype):
            raise ValueError(
                f"{where}: {key} has shape {have[key][0]} {have[key][1]}, the model expects "
                f"{shape} {dtype}; the checkpoint belongs to another configuration"
            )


class MetricWriter:
    """Scalars to `<run>/metrics.jsonl` (one JSON object per line) and TensorBoard `<run>/tb/`.

    With `resume_step`, records after that step (written by the interrupted part of a run) are
    dropped, so that the log of a resumed run reads like one of an uninterrupted run.
    The JSONL file is rewritten atomically on every call (it stays small: one line per log step).
    """

    def __init__(self, run_dir: str | Path, resume_step: int | None = None):
        from tensorboardX import SummaryWriter  # heavy import, only where logging happens

        self.path = Path(run_dir) / METRICS_FILE
        self._lines: list[str] = []
        if self.path.is_file():
            for line in self.path.read_text().splitlines():
                try:
                    record = json.loads(line)
                except json.JSONDecodeError:
                    continue  # a line torn by a crash of an older writer
                if resume_step is None or record.get("step", 0) <= resume_step:
                    self._lines.append(line)
        purge = None if resume_step is None else resume_step + 1
        self._tb = SummaryWriter(str(Path(run_dir) / TENSORBOARD_DIR), purge_step=purge)

    def write_scalars(self, step: int, scalars: Mapping[str, Any]) -> None:
        """Logs `scalars` (name -> number or 0-d array) at `step`."""
        values = {k: float(v) for k, v in scalars.items()}
        self._lines.append(json.dumps({"step": int(step), **values}))
        atomic.write_text(self.path, "\n".join(self._lines) + "\n")
        for name, value in values.items():
            self._tb.add_scalar(name, value, int(step))
        self._tb.flush()

    def close(self) -> None:
        self._tb.close()


class NullWriter:
    """The metric writer of the non-primary hosts: writes nothing."""

    def write_scalars(self, step: int, scalars: Mapping[str, Any]) -> None:
        del step, scalars

    def close(self) -> None:
        pass


def metric_writer(run_dir: str | Path, resume_step: int | None = None) -> Any:
    """`MetricWriter` on process 0 (the one that writes logs), a `NullWriter` on the others."""
    if jax.process_index() == 0:
        return MetricWriter(run_dir, resume_step=resume_step)
    return NullWriter()


def read_metrics(run_dir: str | Path) -> list[dict[str, float]]:
    """Parses `<run_dir>/metrics.jsonl` into a list of records."""
    path = Path(run_dir) / METRICS_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found; has the run logged anything yet?")
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


# --- the training loop ------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Cadence:
    """When the loop logs, validates and checkpoints (every `*_every` steps and at the end)."""

    steps: int
    log_every: int
    val_every: int
    ckpt_every: int
    time_limit_minutes: float = 0.0

    @classmethod
    def of(cls, cfg: Any) -> Cadence:
        return cls(
            cfg.steps,
            cfg.log_every,
            cfg.val_every,
            cfg.ckpt_every,
            getattr(cfg, "time_limit_minutes", 0.0),
        )


class LoopEnd(NamedTuple):
    """Where `train_loop` stopped."""

    start: int  # steps taken before this invocation (a resumed run's checkpoint step)
    step: int  # steps taken when the loop stopped
    state: Any  # the training state then
    validation: dict[str, float]  # the last validation scalars


def train_loop(
    state: Any,
    run: str | Path,
    *,
    resume: bool,
    cadence: Cadence,
    train_step: Callable[[Any, int], tuple[Any, Mapping[str, jax.Array]]],
    validate: Callable[[int, Any], dict[str, float]],
    keep_checkpoints: int,
    best_metric: str | None = None,
    data_iter: grain.DatasetIterator | None = None,
    progress: bool = True,
    desc: str | None = None,
    step_hook: Callable[[int, Any], Any] | None = None,
    postfix: Callable[[], dict[str, str]] | None = None,
) -> LoopEnd:
    """The one training loop of both phases: resume, step, log, validate, checkpoint, stop on NaN.

    It opens the run's checkpoints (`<run>/checkpoints`) and metric log (`metric_writer`), and
    closes both however it ends. With `resume` it first restores the latest checkpoint into the
    structure and placement of `state` (and the position of `data_iter`), and drops the metrics
    logged after that step, so the log reads like one of an uninterrupted run.

    The step's metrics stay on the device; the loop fetches them (one transfer for all the losses
    since the last fetch) only when it logs, validates or checkpoints, so it never waits for a
    step it does not report. A non-finite loss is found at that point, before a checkpoint of
    the broken state could be written.

    Args:
      state: the training state (donated to `train_step`); with `resume` only its structure.
      run: the run folder (made by `prepare_run_dir`).
      resume: continue from the run's latest checkpoint.
      cadence: total steps and the log / validation / checkpoint intervals.
      train_step: `(state, step) -> (state, metrics)`, `step` the steps taken before it; the
        metrics hold "loss".
      validate: `(step, state) -> scalars` (named "val/..."), called every `val_every` steps.
      keep_checkpoints: how many of the latest checkpoints are kept.
      best_metric: a validation scalar; the checkpoint where it was lowest is kept too (saved
        with the validation scalars). None: no best checkpoint.
      data_iter: the grain iterator saved with each checkpoint (exact resume), if any.
      progress, desc: the tqdm bar.
      step_hook: test hook `(step, state) -> state` applied before each step.
      postfix: `() -> {name: text}` shown on the bar beside the loss at every log (what the
        inputs are doing, e.g. phase 2's crops detected so far).

    Returns:
      `LoopEnd`: the resumed step, the steps taken, the final state, the last validation.

    Raises:
      FileNotFoundError, ValueError: `resume` without a checkpoint that fits `state`
        (`Checkpointer.restore`).
      NonFiniteLossError: the loss became NaN/inf; the message gives the first such step, and the
        last good checkpoint stays on disk.
    """
    checkpointer = Checkpointer(Path(run) / CHECKPOINTS, keep_checkpoints, best_metric)
    try:
        start = 0
        if resume:
            start, state = checkpointer.restore(abstract_state(state), data_iter=data_iter)
        writer = metric_writer(run, resume_step=start if resume else None)
        try:
            step, state, last_val = _run_steps(
                state,
                start,
                cadence=cadence,
                train_step=train_step,
                validate=validate,
                checkpointer=checkpointer,
                writer=writer,
                data_iter=data_iter,
                progress=progress,
                desc=desc,
                step_hook=step_hook,
                postfix=postfix,
            )
        finally:
            writer.close()
    finally:
        checkpointer.close()
    return LoopEnd(start, step, state, last_val)


def _run_steps(
    state: Any,
    start: int,
    *,
    cadence: Cadence,
    train_step: Callable[[Any, int], tuple[Any, Mapping[str, jax.Array]]],
    validate: Callable[[int, Any], dict[str, float]],
    checkpointer: Checkpointer,
    writer: Any,
    data_iter: grain.DatasetIterator | None,
    progress: bool,
    desc: str | None,
    step_hook: Callable[[int, Any], Any] | None,
    postfix: Callable[[], dict[str, str]] | None = None,
) -> tuple[int, Any, dict[str, float]]:
    """`train_loop`'s steps from `start` with an open checkpointer and writer: (steps taken,
    final state, the last validation scalars)."""
    from tqdm import tqdm

    pbar = tqdm(
        total=cadence.steps, initial=start, disable=not progress, dynamic_ncols=True, desc=desc
    )
    limit = 60.0 * cadence.time_limit_minutes
    deadline = time.perf_counter() + limit if limit > 0 else math.inf
    t_last, step_last = time.perf_counter(), start
    pending: list[jax.Array] = []  # the losses of the steps since the last fetch, on the device
    last_val: dict[str, float] = {}
    step, last = start, start >= cadence.steps
    try:
        while not last:
            if step_hook is not None:
                state = step_hook(step, state)
            state, metrics = train_step(state, step)
            step += 1
            pending.append(metrics["loss"])
            pbar.update(1)
            last = step >= cadence.steps or time.perf_counter() >= deadline
            log = step % cadence.log_every == 0 or last
            val = step % cadence.val_every == 0 or last
            save = step % cadence.ckpt_every == 0 or last
            if not (log or val or save):
                continue
            _check_finite(jax.device_get(pending), step, checkpointer)
            pending = []
            if log:
                now = time.perf_counter()
                logged = {f"train/{k}": float(v) for k, v in jax.device_get(metrics).items()}
                logged["train/steps_per_s"] = (step - step_last) / max(now - t_last, 1e-9)
                t_last, step_last = now, step
                writer.write_scalars(step, logged)
                pbar.set_postfix(
                    loss=f"{logged['train/loss']:.4g}",
                    steps_s=f"{logged['train/steps_per_s']:.2f}",
                    **(postfix() if postfix is not None else {}),
                )
            val_metrics = None
            if val:
                val_metrics = last_val = validate(step, state)
                writer.write_scalars(step, val_metrics)
                pbar.write(
                    f"step {step}: "
                    + " ".join(f"{k[4:]}={v:.4g}" for k, v in sorted(val_metrics.items()))
                )
            if save and step not in checkpointer.all_steps():
                best = val_metrics if checkpointer.best_metric is not None else None
                checkpointer.save(step, state, metrics=best, data_iter=data_iter)
    finally:
        pbar.close()
    return step, state, last_val


def _check_finite(losses: list[Any], step: int, checkpointer: Checkpointer) -> None:
    """Raises NonFiniteLossError naming the first non-finite loss of the steps ending at `step`."""
    for offset, loss in enumerate(losses):
        if not math.isfinite(float(loss)):
            bad = step - len(losses) + 1 + offset
            raise NonFiniteLossError(
                f"loss became {float(loss)} at step {bad}; training stopped. The last good "
                f"checkpoint (step {checkpointer.latest_step()}) in {checkpointer.directory} is "
                "kept; lower learning_rate or clip_norm and resume or restart"
            )
