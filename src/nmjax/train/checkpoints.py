"""Orbax checkpoints of a training state (`Checkpointer`), the check that a checkpoint fits the
model it is restored into, and the start of a fine-tuning run from another run's weights.
"""

from __future__ import annotations

import gc
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import grain
import jax
import numpy as np
import orbax.checkpoint as ocp
from orbax.checkpoint import checkpoint_managers as ocp_policies

from nmjax import run_folder
from nmjax.config_io import flatten_config


def abstract_state(state: Any) -> Any:
    """Shapes, dtypes and shardings of `state`: a restore target that keeps its placement."""
    return jax.tree.map(
        lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=getattr(x, "sharding", None)),
        state,
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
    if not (source / run_folder.CONFIG_FILE).is_file():
        raise FileNotFoundError(
            f"--init-from {source}: no {run_folder.CONFIG_FILE} there; give a {phase} run folder "
            "(one that `nmjax train-...` or `nmjax import-release` wrote)"
        )
    try:
        saved = run_folder.load_config(source, type(config))
    except (ValueError, TypeError) as err:
        raise ValueError(f"--init-from {source} is not a {phase} run ({err})") from err
    if not run_folder.checkpoint_steps(source):
        raise FileNotFoundError(f"--init-from {source}: the run has no complete checkpoint")
    old, new = flatten_config(saved), flatten_config(config)
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


# The parts of a training state (`optim.init_state`), each saved as its own checkpoint item so
# that inference restores the model alone, without building an optimizer state.
STATE_PARTS = ("model", "opt", "ema")
# The one item that held the whole state in checkpoints written before the parts were split.
LEGACY_STATE_ITEM = "state"


class Checkpointer:
    """One `ocp.CheckpointManager`: the last `keep` checkpoints plus the best by `best_metric`,
    plus every checkpoint whose step is a multiple of `keep_every` (0: none), which the retention
    policy never deletes (a run scored along its training, `experiments/phase1_budget.py`).

    A checkpoint holds one item per part of the training state {"model", "opt"[, "ema"]}
    (`STATE_PARTS`) and, when given, the item `data` (the grain iterator's position); a
    checkpoint written before the split holds the whole state as the one item "state" and
    still restores (`restore`, `restore_parts`). Saves are synchronous so a checkpoint is
    complete on disk when `save` returns, before the next step donates the buffers. Existing
    checkpoints are never overwritten or deleted except by the retention policy.
    """

    def __init__(
        self,
        directory: str | Path,
        keep: int = 3,
        best_metric: str | None = None,
        keep_every: int = 0,
    ):
        if keep < 1:
            raise ValueError(f"keep_checkpoints must be >= 1, got {keep}")
        if keep_every < 0:
            raise ValueError(f"keep_every must be >= 0 (0: none), got {keep_every}")
        self.directory = Path(directory).absolute()
        self.best_metric = best_metric
        policies: list[Any] = [ocp_policies.LatestN(n=keep)]
        if keep_every:
            policies.append(ocp_policies.EveryNSteps(interval_steps=keep_every))
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
        # Named handlers let a fresh process read a checkpoint's metadata before restoring.
        handlers: dict[str, Any] = {
            name: ocp.StandardCheckpointHandler() for name in (*STATE_PARTS, LEGACY_STATE_ITEM)
        }
        handlers["data"] = grain.checkpoint.CheckpointHandler()
        self._manager = ocp.CheckpointManager(
            self.directory, options=options, item_handlers=handlers
        )

    @classmethod
    def of_run(cls, run: str | Path, loop: Any, best_metric: str | None = None) -> Checkpointer:
        """The checkpoints of run folder `run`, kept as its `LoopConfig` `loop` says."""
        return cls(
            run_folder.checkpoint_dir(run), loop.keep_checkpoints, best_metric, loop.keep_every
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
        state: Mapping[str, Any],
        metrics: Mapping[str, Any] | None = None,
        data_iter: grain.DatasetIterator | None = None,
    ) -> None:
        """Writes checkpoint `step` of `state` ({"model", "opt"[, "ema"]}, one item each);
        refuses to overwrite an existing one."""
        if step in self._manager.all_steps():
            raise ValueError(
                f"checkpoint {step} already exists in {self.directory}; refusing to overwrite it"
            )
        unknown = sorted(set(state) - set(STATE_PARTS))
        if unknown or "model" not in state:
            raise ValueError(
                f"a training state has the parts {STATE_PARTS} (with 'model'); got {sorted(state)}"
            )
        items: dict[str, Any] = {k: ocp.args.StandardSave(v) for k, v in state.items()}
        if data_iter is not None:
            items["data"] = grain.checkpoint.CheckpointSave(data_iter)
        if metrics is not None:
            metrics = {k: float(v) for k, v in metrics.items()}
        self._manager.save(step, args=ocp.args.Composite(**items), metrics=metrics, force=True)

    def _step(self, step: int | None) -> int:
        steps = self.all_steps()
        if step is None:
            if not steps:
                raise FileNotFoundError(f"no checkpoint found in {self.directory}")
            return steps[-1]
        if step not in steps:
            raise FileNotFoundError(
                f"checkpoint {step} not found in {self.directory}; available steps: {steps}"
            )
        return step

    def restore(
        self,
        abstract_state: Mapping[str, Any],
        step: int | None = None,
        data_iter: grain.DatasetIterator | None = None,
    ) -> tuple[int, Any]:
        """Restores checkpoint `step` (default: the latest) into the structure of `abstract_state`.

        Args:
          abstract_state: {part: pytree of `jax.ShapeDtypeStruct` (e.g. from `nnx.eval_shape`) or
            arrays}, the whole training state.
          step: which checkpoint; None = the latest.
          data_iter: grain iterator whose position is restored in place, when given.

        Returns:
          (step, state).

        Raises:
          FileNotFoundError: there is no checkpoint (or not that step).
          ValueError: the checkpoint is corrupt or belongs to a different model/configuration.
        """
        step = self._step(step)
        return step, self._restore(step, dict(abstract_state), data_iter, whole=True)

    def restore_parts(
        self,
        abstract_parts: Mapping[str, Any],
        step: int | None = None,
        whole_state: Callable[[], Mapping[str, Any]] | None = None,
    ) -> tuple[int, dict[str, Any]]:
        """Restores only the parts `abstract_parts` names (e.g. {"model": ...}) of checkpoint
        `step`: what inference needs, without an optimizer state.

        A checkpoint of the earlier layout holds the whole state in one item, which restores
        only whole: `whole_state()` then gives its abstract structure (it is not called for a
        checkpoint of parts).

        Raises:
          FileNotFoundError: no checkpoint (or not that step).
          ValueError: a part the checkpoint lacks, a mismatch, or damaged files.
        """
        step = self._step(step)
        if self._legacy(step):
            if whole_state is None:
                raise ValueError(
                    f"checkpoint {step} in {self.directory} holds the whole training state in "
                    "one item; restoring a part of it needs the whole state's structure"
                )
            state = self._restore(step, dict(whole_state()), None, whole=True)
            return step, {name: state[name] for name in abstract_parts}
        return step, self._restore(step, dict(abstract_parts), None, whole=False)

    def _legacy(self, step: int) -> bool:
        try:
            saved = self._manager.item_metadata(step)
        except Exception:  # damaged metadata: the restore reports it in one line
            return False
        return saved.get(LEGACY_STATE_ITEM) is not None and saved.get("model") is None

    def _restore(
        self,
        step: int,
        abstract: dict[str, Any],
        data_iter: grain.DatasetIterator | None,
        whole: bool,
    ) -> dict[str, Any]:
        where = f"checkpoint {step} in {self.directory}"
        legacy = self._legacy(step)
        if legacy:
            items: dict[str, Any] = {LEGACY_STATE_ITEM: ocp.args.StandardRestore(abstract)}
        else:
            items = {k: ocp.args.StandardRestore(v) for k, v in abstract.items()}
        if data_iter is not None:
            items["data"] = grain.checkpoint.CheckpointRestore(data_iter)
        failure = None
        try:
            # Refuse a mismatched checkpoint from its metadata, before any array read starts:
            # orbax abandons the in-flight reads of a failed restore to a closed event loop.
            saved = self._manager.item_metadata(step)
        except Exception as err:  # orbax/tensorstore raise many types for damaged files
            failure = err
        else:
            if legacy:
                saved_state = saved[LEGACY_STATE_ITEM]
            else:
                parts = [k for k in STATE_PARTS if saved.get(k) is not None]
                if set(abstract) - set(parts) or (whole and set(parts) != set(abstract)):
                    raise ValueError(
                        f"{where} holds the parts {parts}, the model asks for "
                        f"{sorted(abstract)}; it was written by another configuration (start a "
                        "new run or use the run's own config)"
                    )
                saved_state = {k: saved[k] for k in abstract}
            _check_compatible(abstract, saved_state, where)
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
        if legacy:
            return dict(restored[LEGACY_STATE_ITEM])
        return {k: restored[k] for k in abstract}

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
