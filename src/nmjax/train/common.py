"""Pieces shared by both trainers: optimizer, run folders, orbax checkpoints, metric logging.

A training state is the pytree `nnx.state((model, optimizer))` of a model and its
`nnx.Optimizer`, split once with `nnx.split`; the trainers jit a step over that pytree and hand it
to `Checkpointer` unchanged.
"""

from __future__ import annotations

import dataclasses
import gc
import json
import math
import shutil
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import grain
import jax
import numpy as np
import optax
import orbax.checkpoint as ocp
from orbax.checkpoint import checkpoint_managers as ocp_policies

from nmjax import io

CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.jsonl"


def make_optimizer(
    learning_rate: float,
    milestones: tuple[int, ...] = (),
    decay: tuple[float, ...] = (),
    clip_norm: float | None = 1.0,
) -> optax.GradientTransformation:
    """Gradient clipping by global norm, then Adam with a piecewise-constant learning rate.

    The rate is `learning_rate` until `milestones[0]`, `learning_rate * decay[0]` until
    `milestones[1]`, then `learning_rate * decay[1]` (paper Table 3: decay [0.25, 0.1]; each factor
    is relative to the initial rate, not compounded).

    Args:
      learning_rate: initial Adam step size.
      milestones: increasing optimizer steps at which the rate changes.
      decay: factor of the initial rate from each milestone on; same length as `milestones`.
      clip_norm: maximum global gradient norm; None or <= 0 disables clipping.

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
    adam = optax.adam(schedule)
    if clip_norm is None or clip_norm <= 0:
        return adam
    return optax.chain(optax.clip_by_global_norm(clip_norm), adam)


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


def prepare_run_dir(
    path: str | Path, *, resume: bool, config: Any, overwrite: bool = False
) -> Path:
    """Creates (or reopens, with `resume`) a run folder and writes `config.json` into it.

    Args:
      path: the run folder.
      resume: continue an existing run; the folder must exist.
      config: a dataclass; `dataclasses.asdict(config)` is written to `<path>/config.json`.
      overwrite: delete an existing folder and start afresh (ignored with `resume`).

    Returns:
      The run folder as a Path.

    Raises:
      FileNotFoundError: `resume` and the folder does not exist.
      ValueError: the folder exists and holds files, and neither `resume` nor `overwrite` is set.
    """
    path = Path(path)
    if resume:
        if not path.is_dir():
            raise FileNotFoundError(
                f"cannot resume: run folder {path} does not exist; drop --resume to start a new run"
            )
    elif path.exists() and (not path.is_dir() or any(path.iterdir())):
        if not overwrite:
            raise ValueError(
                f"run folder {path} already exists; pass --resume to continue it, --overwrite to "
                "replace it, or choose another --run"
            )
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink()
    path.mkdir(parents=True, exist_ok=True)
    io.write_json(path / CONFIG_FILE, config_to_dict(config))
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

    def wait(self) -> None:
        self._manager.wait_until_finished()

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
        self._tb = SummaryWriter(str(Path(run_dir) / "tb"), purge_step=purge)

    def write_scalars(self, step: int, scalars: Mapping[str, Any]) -> None:
        """Logs `scalars` (name -> number or 0-d array) at `step`."""
        values = {k: float(v) for k, v in scalars.items()}
        self._lines.append(json.dumps({"step": int(step), **values}))
        io.write_text(self.path, "\n".join(self._lines) + "\n")
        for name, value in values.items():
            self._tb.add_scalar(name, value, int(step))
        self._tb.flush()

    def close(self) -> None:
        self._tb.close()


def read_metrics(run_dir: str | Path) -> list[dict[str, float]]:
    """Parses `<run_dir>/metrics.jsonl` into a list of records."""
    path = Path(run_dir) / METRICS_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found; has the run logged anything yet?")
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
