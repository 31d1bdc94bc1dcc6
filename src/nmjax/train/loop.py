"""The one training loop of both phases (`train_loop`): resume, step, log, validate, checkpoint,
stop on a non-finite loss or at the time limit.

A training state is the pytree {"model", "opt"[, "ema"]} of `optim.init_state`; each phase jits
one module-level step over it (graphdef and settings static, state donated), and `train_loop`
drives it: it opens the run's checkpoints and metric log, restores a resumed run, hands the state
to `Checkpointer` unchanged and logs what the step returns.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import grain
import jax

from nmjax.config import LoopConfig
from nmjax.train.checkpoints import Checkpointer, abstract_state
from nmjax.train.metric_log import metric_writer


class NonFiniteLossError(RuntimeError):
    """The training loss became NaN or infinite."""


def check_positive(values: dict[str, int]) -> None:
    """Raises ValueError naming the first of `values` ({field: value}) that is below 1."""
    for name, value in values.items():
        if value < 1:
            raise ValueError(f"{name} must be >= 1, got {value}")


def check_loop(loop: LoopConfig) -> None:
    """Refuses (ValueError naming the field) a cadence the loop cannot keep."""
    check_positive(
        {
            "log_every": loop.log_every,
            "val_every": loop.val_every,
            "ckpt_every": loop.ckpt_every,
            "keep_checkpoints": loop.keep_checkpoints,
        }
    )
    if not loop.time_limit_minutes >= 0:
        raise ValueError(
            f"time_limit_minutes must be >= 0 (0: no limit), got {loop.time_limit_minutes}"
        )


class LoopEnd(NamedTuple):
    """Where `train_loop` stopped."""

    start: int  # steps taken before this invocation (a resumed run's checkpoint step)
    step: int  # steps taken when the loop stopped
    state: Any  # the training state then
    validation: dict[str, float]  # the last validation scalars


@dataclasses.dataclass(frozen=True)
class TrainSummary:
    """What each phase's entry returns (`skel.train_skeleton`, `dyn.train_dynamics`).

    Attributes:
      run: the run folder.
      start_step: steps taken before this invocation (a resumed run's checkpoint step, else 0).
      step: steps taken when training stopped.
      stop_reason: "steps" (`loop.steps` reached) or "time_limit" (`loop.time_limit_minutes`
        passed first); a non-finite loss raises `NonFiniteLossError` instead.
      validation: the last validation scalars ("val/..."), empty when none ran (a resumed run
        that was already at its end).
    """

    run: Path
    start_step: int
    step: int
    stop_reason: str
    validation: dict[str, float]

    @classmethod
    def of(cls, run: Path, end: LoopEnd, loop: LoopConfig) -> TrainSummary:
        reason = "steps" if end.step >= loop.steps else "time_limit"
        return cls(Path(run), end.start, end.step, reason, dict(end.validation))


def train_loop(
    state: Any,
    run: str | Path,
    *,
    resume: bool,
    loop: LoopConfig,
    train_step: Callable[[Any, int], tuple[Any, Mapping[str, jax.Array]]],
    validate: Callable[[int, Any], dict[str, float]],
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
      loop: total steps, the log / validation / checkpoint intervals, the checkpoints kept and
        the time limit.
      train_step: `(state, step) -> (state, metrics)`, `step` the steps taken before it; the
        metrics hold "loss".
      validate: `(step, state) -> scalars` (named "val/..."), called every `val_every` steps.
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
    checkpointer = Checkpointer.of_run(run, loop, best_metric)
    try:
        start = 0
        if resume:
            start, state = checkpointer.restore(abstract_state(state), data_iter=data_iter)
        writer = metric_writer(run, resume_step=start if resume else None)
        try:
            step, state, last_val = _run_steps(
                state,
                start,
                loop=loop,
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
    loop: LoopConfig,
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
        total=loop.steps, initial=start, disable=not progress, dynamic_ncols=True, desc=desc
    )
    limit = 60.0 * loop.time_limit_minutes
    deadline = time.perf_counter() + limit if limit > 0 else math.inf
    t_last, step_last = time.perf_counter(), start
    pending: list[jax.Array] = []  # the losses of the steps since the last fetch, on the device
    last_val: dict[str, float] = {}
    step, last = start, start >= loop.steps
    try:
        while not last:
            if step_hook is not None:
                state = step_hook(step, state)
            state, metrics = train_step(state, step)
            step += 1
            pending.append(metrics["loss"])
            pbar.update(1)
            last = step >= loop.steps or time.perf_counter() >= deadline
            log = step % loop.log_every == 0 or last
            val = step % loop.val_every == 0 or last
            save = step % loop.ckpt_every == 0 or last
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
