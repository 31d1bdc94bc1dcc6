"""The optimiser of both phases: Adam with a piecewise-constant learning rate, optional clipping
by global norm, Adam's per-epoch restarts (as the release builds a new optimizer every epoch) and
an optional weight average; the training state {"model", "opt"[, "ema"]} they update.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import nnx

from nmjax.config import OPTIMIZER_RESETS, LoopConfig, OptimConfig


def check_schedule(optim: OptimConfig, loop: LoopConfig) -> None:
    """Refuses (ValueError naming the field) a schedule that cannot run: no length, decays that
    do not fit it, an unknown optimizer_reset, a weight average's decay outside [0, 1). Phase 1
    and phase 2 share it."""
    if optim.optimizer_reset not in OPTIMIZER_RESETS:
        raise ValueError(
            f"optimizer_reset must be one of {', '.join(OPTIMIZER_RESETS)}, got "
            f"{optim.optimizer_reset!r}"
        )
    if loop.epochs < 0:
        raise ValueError(f"epochs must be >= 0 (0: a step count instead), got {loop.epochs}")
    if loop.epochs == 0 and loop.steps < 1:
        raise ValueError(f"steps must be >= 1 when epochs = 0, got {loop.steps}")
    decays = optim.decay_epochs
    if loop.epochs > 0 and any(not 0 < e < loop.epochs for e in decays):
        raise ValueError(f"decay_epochs {decays} must lie inside the run's {loop.epochs} epochs")
    if not 0 <= optim.ema_decay < 1:
        raise ValueError(
            f"ema_decay must be in [0, 1) (0: no weight average; e.g. 0.99), got {optim.ema_decay}"
        )


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
        """From a train config of either phase (its `optim` and `loop` groups).

        The epochs must be resolved (`config.resolve_epochs`) for the restarts and decays to be
        in it: a configuration that is not (a benchmark of the step) gets the decays that are
        already in steps and the restarting state's layout without restarts, so its checkpoints
        have the layout of the resolved run's.
        """
        optim: OptimConfig = cfg.optim
        milestones = tuple(optim.lr_milestones)
        decay = tuple(optim.lr_decay)[: len(milestones)]
        period = cfg.loop.steps_per_epoch if optim.optimizer_reset == "epoch" else None
        return cls(optim.learning_rate, milestones, decay, optim.clip_norm, optim.ema_decay, period)

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
