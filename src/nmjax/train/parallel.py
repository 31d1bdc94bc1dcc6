"""Data parallelism for both trainers: one device mesh, sharded batches, replicated state, hosts.

Every train step runs on a `jax.sharding.Mesh` with one axis, "data", over all devices JAX sees
(all hosts together). The batch axis is sharded over it (`P("data")`); parameters and optimizer
state are replicated (`P()`), so XLA inserts the gradient all-reduce. One device is the same code
path with a mesh of one device.

Several hosts join with `jax.distributed.initialize`, driven by the `--coordinator-address`,
`--num-processes`, `--process-id` flags of `nmjax train-skel` / `nmjax train-dyn`
(`nmjax.cli.train`) or, when the flags are absent, by the environment variables
JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES, JAX_PROCESS_ID. Each host then feeds its own slice
of the global batch (`host_batch_to_global`); arrays every host holds in full (validation
batches, the phase-2 crop table, the initial state) are placed with `global_array` /
`replicate`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np
from jax.sharding import AxisType, Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from nmjax.config import check_batch_split

DATA_AXIS = "data"
ENV_COORDINATOR = "JAX_COORDINATOR_ADDRESS"
ENV_NUM_PROCESSES = "JAX_NUM_PROCESSES"
ENV_PROCESS_ID = "JAX_PROCESS_ID"


# --- several hosts ---------------------------------------------------------------------------


def distributed_settings(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    env: Mapping[str, str] | None = None,
) -> tuple[str, int, int] | None:
    """(coordinator address, process count, process id) from the flags, else the environment.

    Returns None when neither names a coordinator (a single-host run).

    Raises:
      ValueError: a coordinator without a process count or id, or an id out of range.
    """
    env = os.environ if env is None else env
    address = coordinator_address or env.get(ENV_COORDINATOR) or None
    if address is None:
        if num_processes is not None or process_id is not None:
            raise ValueError(
                "--num-processes / --process-id need --coordinator-address HOST:PORT "
                f"(or ${ENV_COORDINATOR}) naming process 0"
            )
        return None
    count = _integer(num_processes, env, ENV_NUM_PROCESSES, "--num-processes")
    index = _integer(process_id, env, ENV_PROCESS_ID, "--process-id")
    if count < 1 or not 0 <= index < count:
        raise ValueError(
            f"--process-id must be in 0..{count - 1} for --num-processes {count}, got {index}"
        )
    return address, count, index


def _integer(value: int | None, env: Mapping[str, str], var: str, flag: str) -> int:
    if value is not None:
        return int(value)
    text = env.get(var)
    if text is None:
        raise ValueError(f"a multi-host run needs {flag} (or ${var}) next to the coordinator")
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"${var} must be an integer, got {text!r}") from None


def initialize_distributed(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
) -> bool:
    """Joins a multi-host run with `jax.distributed.initialize`; returns False for one host.

    Call it before anything touches devices (it must precede backend initialisation).
    """
    settings = distributed_settings(coordinator_address, num_processes, process_id)
    if settings is None:
        return False
    address, count, index = settings
    jax.distributed.initialize(address, num_processes=count, process_id=index)
    return True


def is_primary() -> bool:
    """True on process 0, the one that writes logs, figures and artefacts."""
    return jax.process_index() == 0


def sync(name: str) -> None:
    """Waits until every process reaches this point (nothing to do on one host)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def prepare_run_dir(path: str | Path, **kwargs: Any) -> Path:
    """`run_folder.prepare_run_dir` on process 0 only; the others wait for it (shared
    filesystem)."""
    from nmjax import run_folder

    if is_primary():
        path = run_folder.prepare_run_dir(path, **kwargs)
    sync(f"prepare_run_dir {path}")
    return Path(path)


# --- the mesh and placement -------------------------------------------------------------------


def data_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A one-axis mesh ("data") over `devices` (default: every device of every host)."""
    devices = list(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("data_mesh needs at least one device")
    return jax.make_mesh((len(devices),), (DATA_AXIS,), (AxisType.Auto,), devices=devices)


def batch_sharding(mesh: Mesh) -> NamedSharding:
    """Leading (batch) axis split over the "data" axis."""
    return NamedSharding(mesh, P(DATA_AXIS))


def replicated(mesh: Mesh) -> NamedSharding:
    """A full copy on every device."""
    return NamedSharding(mesh, P())


def check_batch_size(batch_size: int, field: str, mesh: Mesh, option: str | None = None) -> None:
    """Refuses a global batch that does not split evenly over the mesh (before compiling).

    Args:
      batch_size: the global batch size B.
      field: the config field it comes from, named in the message (e.g. "data.batch_size").
      mesh: the data mesh.
      option: the command-line option that sets it, for the fix (e.g. "--batch-size ").
    """
    devices = mesh.devices.size
    check_batch_split(
        batch_size,
        devices,
        field,
        f"{devices} devices ({jax.process_count()} host(s))",
        option,
        ", or run on fewer devices (CUDA_VISIBLE_DEVICES)",
    )


def host_batch_to_global(local: Any, mesh: Mesh) -> Any:
    """Each host's slice of a batch (leaves (B / hosts, ...)) -> global (B, ...) on P("data").

    The global batch is the concatenation of the hosts' slices in process order.
    """
    sharding = batch_sharding(mesh)
    return jax.tree.map(
        lambda x: jax.make_array_from_process_local_data(sharding, np.asarray(x)), local
    )


def global_array(full: Any, mesh: Mesh, sharded: bool = True) -> Any:
    """Arrays every host holds in full -> global arrays, batch-sharded or (`sharded=False`)
    replicated. Works for typed PRNG keys too."""
    sharding = batch_sharding(mesh) if sharded else replicated(mesh)

    def place(x: Any) -> Any:
        if isinstance(x, jax.Array) and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            return jax.random.wrap_key_data(
                place(jax.random.key_data(x)), impl=jax.random.key_impl(x)
            )
        host = np.asarray(x)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree.map(place, full)


def replicate(tree: Any, mesh: Mesh) -> Any:
    """A pytree of arrays (the same on every host) replicated on every device of the mesh."""
    return global_array(tree, mesh, sharded=False)


def constrain_batch(x: Any, mesh: Mesh) -> Any:
    """Inside jit: the leading axis of every leaf of `x` sharded over "data".

    On a one-device mesh there is nothing to split and no annotation is added, so arrays given on
    that device keep their placement (and a jitted step its single compilation).
    """
    if mesh.devices.size == 1:
        return x
    return jax.lax.with_sharding_constraint(x, batch_sharding(mesh))


def constrain_replicated(tree: Any, mesh: Mesh) -> Any:
    """Inside jit: every leaf of `tree` replicated (e.g. outputs fetched by every host); no
    annotation on a one-device mesh (see `constrain_batch`)."""
    if mesh.devices.size == 1:
        return tree
    return jax.lax.with_sharding_constraint(tree, replicated(mesh))


def to_local(tree: Any) -> Any:
    """Replicated global arrays -> copies on this host's first device (for local-only work)."""
    return jax.device_put(jax.device_get(tree), jax.local_devices()[0])
