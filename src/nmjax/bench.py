"""Benchmarks of the train steps (`nmjax bench`) and of the optimisations in the code.

    nmjax bench [--phase skel dyn] [--preset cpu default] [--data synth-arm] [--steps N]
                [--warmup N] [--set FIELD=VALUE ...] [--compute-dtype float32|bfloat16]
                [--out FILE.json]

For each (phase, preset) one row: steps/s and frames/s (B*T per step), seconds per step spent
waiting for data vs computing, compile time and peak memory.

- Phase 1 (`nmjax.train.skel`): the real grain pipeline of `--data` (a synthetic set is generated
  on first use, outside the timings). Per step, "load" is the wait for the next batch from the
  grain iterator plus the host -> device placement (`skel.device_batch`, blocked until ready);
  "compute" is the compiled step until its outputs are ready. steps/s counts both.
- Phase 2 (`nmjax.train.dyn`): random-walk keypoint trajectories on a hand-like tree (five chains
  from the root) stand in for a phase-1 run; the step's cost does not depend on the values. Its
  crops are gathered on the device inside the step, so there is no host loading (load = 0).

Compile time is `jit(...).lower(...).compile()`, timed on its own; the compiled executable is then
the one that runs. Memory: the compiled step's `memory_analysis()` (argument, output, temporary
bytes) and the device's `memory_stats()["peak_bytes_in_use"]` where it reports one (GPU), else the
process's peak resident set size (`resource.getrusage`). Both only grow within a process, so with
several rows each row is measured in a fresh process (`--same-process` to opt out).

`optimisations_main` (experiments/bench_optimisations.py) times each optimisation in the code
against its plain formulation, forward + backward, in one process; the `plain_*` / `fast_*` pairs
below are the two formulations and are tested to agree.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from nmjax import atomic
from nmjax.config import (
    PRESETS,
    add_override_argument,
    apply_overrides,
    dataset_spec,
    dyn_preset,
    skel_preset,
)

PHASES = ("skel", "dyn")
MEMORY_KEYS = ("argument_bytes", "output_bytes", "temp_bytes")


# --- environment ------------------------------------------------------------------------------


def environment() -> dict[str, Any]:
    """The header of every benchmark: devices, versions, CPU count and 1-minute load average."""
    devices = jax.devices()
    return {
        "devices": [f"{d.platform}:{d.device_kind}" for d in devices],
        "device_count": len(devices),
        "backend": jax.default_backend(),
        "jax": jax.__version__,
        "cpu_count": os.cpu_count(),
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def memory_of(compiled: Any) -> dict[str, int]:
    """Argument / output / temporary bytes of a compiled executable, plus the process peak.

    `peak_bytes_in_use` comes from the first device's `memory_stats()` when it has one (GPU/TPU);
    otherwise `peak_rss_bytes` is the process's peak resident set size.
    """
    analysis = compiled.memory_analysis()
    out: dict[str, int] = {}
    if analysis is not None:
        out["argument_bytes"] = int(analysis.argument_size_in_bytes)
        out["output_bytes"] = int(analysis.output_size_in_bytes)
        out["temp_bytes"] = int(analysis.temp_size_in_bytes)
    stats = jax.local_devices()[0].memory_stats()
    if stats and "peak_bytes_in_use" in stats:
        out["peak_bytes_in_use"] = int(stats["peak_bytes_in_use"])
    else:
        out["peak_rss_bytes"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return out


def _timed_compile(jitted: Any, *args: Any, **kwargs: Any) -> tuple[Any, float]:
    tic = time.perf_counter()
    compiled = jitted.lower(*args, **kwargs).compile()
    return compiled, time.perf_counter() - tic


def _row(
    phase: str,
    preset: str,
    shape: dict[str, Any],
    load: list[float],
    compute: list[float],
    compile_s: float,
    memory: dict[str, int],
    note: str,
) -> dict[str, Any]:
    steps = len(compute)
    total = sum(load) + sum(compute)
    frames = shape["B"] * shape["T"]
    return {
        "phase": phase,
        "preset": preset,
        **shape,
        "steps": steps,
        "steps_per_s": steps / total,
        "frames_per_s": steps * frames / total,
        "load_s_per_step": sum(load) / steps,
        "compute_s_per_step": sum(compute) / steps,
        "compute_s_median": statistics.median(compute),
        "compute_s_steps": compute,
        "compile_s": compile_s,
        "memory": memory,
        "data": note,
    }


# --- phase 1 ----------------------------------------------------------------------------------


def bench_skel(cfg: Any, preset: str, steps: int, warmup: int) -> dict[str, Any]:
    """Times the phase-1 train step of `cfg` (a SkelTrainConfig) on its real data pipeline."""
    from nmjax.data import pipeline
    from nmjax.data.synthetic import ensure_dataset
    from nmjax.train import parallel, skel

    skel.check_config(cfg)
    ensure_dataset(cfg.data.name, cfg.data.root)  # a synthetic set is generated here, untimed
    mesh = parallel.data_mesh()
    parallel.check_batch_size(
        cfg.data.batch_size, "data.batch_size", mesh, "--set skel:data.batch_size="
    )
    graphdef, state = skel.build(cfg)
    state = parallel.replicate(state, mesh)
    data_iter = pipeline.skel_iterator(cfg.data, "train", seed=cfg.seed)
    inputs = skel.device_batch(next(data_iter), cfg, mesh)
    settings = skel.StepSettings.of(cfg)
    compiled, compile_s = _timed_compile(
        skel.train_step, state, inputs, graphdef=graphdef, settings=settings, mesh=mesh
    )
    load, compute = [], []
    for i in range(warmup + steps):
        tic = time.perf_counter()
        inputs = jax.block_until_ready(skel.device_batch(next(data_iter), cfg, mesh))
        toc = time.perf_counter()
        state, scalars = jax.block_until_ready(compiled(state, inputs))
        if i >= warmup:
            load.append(toc - tic)
            compute.append(time.perf_counter() - toc)
    if not np.isfinite(float(scalars["loss"])):
        raise RuntimeError(f"bench: phase-1 loss became {float(scalars['loss'])}")
    m = cfg.model
    shape = {
        "data_name": cfg.data.name,
        "B": cfg.data.batch_size,
        "T": cfg.data.frames,
        "G": m.grid,
        "C": m.channels,
        "K": m.num_keypoints,
        "compute_dtype": m.compute_dtype,
    }
    note = (
        f"grain pipeline (prefetch={cfg.data.prefetch}, workers={cfg.data.worker_count}); "
        "load = wait for the batch + host->device placement"
    )
    return _row("skel", preset, shape, load, compute, compile_s, memory_of(compiled), note)


# --- phase 2 ----------------------------------------------------------------------------------


def hand_tree(num_keypoints: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """(parents, order) of a hand-like tree: five chains from the root, depth about K / 5."""
    parents = tuple(max(k - 5, 0) for k in range(num_keypoints))
    return parents, tuple(range(num_keypoints))


def random_walk(num_keypoints: int, frames: int = 400, seed: int = 0) -> np.ndarray:
    """(frames, K, 4) float32 random-walk keypoint trajectories (xyz and alpha)."""
    rng = np.random.default_rng(seed)
    steps = rng.normal(scale=0.01, size=(frames, num_keypoints, 4))
    return np.cumsum(steps, axis=0).astype(np.float32)


def bench_dyn(cfg: Any, preset: str, num_keypoints: int, steps: int, warmup: int) -> dict:
    """Times the phase-2 train step of `cfg` (a DynTrainConfig) on random-walk trajectories."""
    from nmjax.train import dyn, parallel

    mesh = parallel.data_mesh()
    parallel.check_batch_size(cfg.batch_size, "batch_size", mesh, "--set dyn:batch_size=")
    parents, order = hand_tree(num_keypoints)
    table = dyn.crop_table({"walk": random_walk(num_keypoints)}, cfg.frames)
    poses, starts, key = parallel.replicate((*table, jax.random.key(cfg.seed)), mesh)
    graphdef, state = dyn.build(cfg, parents, order)
    state = parallel.replicate(state, mesh)
    settings = dyn.StepSettings.of(cfg)
    compiled, compile_s = _timed_compile(
        dyn.train_step,
        state,
        poses,
        starts,
        key,
        jnp.int32(0),
        graphdef=graphdef,
        settings=settings,
        mesh=mesh,
    )
    load, compute = [], []
    for i in range(warmup + steps):
        tic = time.perf_counter()
        state, metrics = jax.block_until_ready(compiled(state, poses, starts, key, jnp.int32(i)))
        if i >= warmup:
            load.append(0.0)
            compute.append(time.perf_counter() - tic)
    if not np.isfinite(float(metrics["loss"])):
        raise RuntimeError(f"bench: phase-2 loss became {float(metrics['loss'])}")
    m = cfg.model
    shape = {
        "model": m.model,
        "B": cfg.batch_size,
        "T": cfg.frames,
        "K": num_keypoints,
        "S": m.posterior_samples,
        "D_z": m.latent,
        "D_h": m.hidden,
        "compute_dtype": "float32",
    }
    note = "crops gathered on the device inside the step (no host loading)"
    return _row("dyn", preset, shape, load, compute, compile_s, memory_of(compiled), note)


# --- command line -----------------------------------------------------------------------------


def _split_overrides(assignments: Sequence[str], phase: str) -> list[str]:
    """The --set items for `phase`: "skel:FIELD=V" / "dyn:FIELD=V" for one phase, plain for both."""
    out = []
    for item in assignments:
        prefix, _, rest = item.partition(":")
        if rest and prefix in PHASES and "=" not in prefix:
            if prefix == phase:
                out.append(rest)
        else:
            out.append(item)
    return out


def configs(args: argparse.Namespace, phase: str, preset: str) -> Any:
    """The preset's config of `phase` with the --set overrides, --compute-dtype and --dyn-model."""
    if phase == "skel":
        cfg = skel_preset(args.data, preset)
        if args.compute_dtype is not None:
            model = dataclasses.replace(cfg.model, compute_dtype=args.compute_dtype)
            cfg = dataclasses.replace(cfg, model=model)
    else:
        cfg = dyn_preset(args.data, preset)
    return apply_overrides(cfg, _split_overrides(args.overrides, phase))


def format_table(rows: list[dict[str, Any]]) -> str:
    """A fixed-width text table of benchmark rows."""
    header = (
        f"{'phase':<5} {'preset':<12} {'dtype':<8} {'B':>3} {'T':>3} {'steps/s':>9} "
        f"{'frames/s':>9} {'load s':>8} {'compute s':>10} {'compile s':>10} {'peak MiB':>9} "
        f"{'temp MiB':>9}"
    )
    lines = [header, "-" * len(header)]
    for r in rows:
        mem = r["memory"]
        peak = mem.get("peak_bytes_in_use", mem.get("peak_rss_bytes", 0)) / 2**20
        label = r["preset"] if r["phase"] == "skel" else f"{r['preset']}/{r['model']}"
        lines.append(
            f"{r['phase']:<5} {label:<12} {r['compute_dtype']:<8} {r['B']:>3} {r['T']:>3} "
            f"{r['steps_per_s']:>9.3f} {r['frames_per_s']:>9.2f} {r['load_s_per_step']:>8.4f} "
            f"{r['compute_s_per_step']:>10.4f} {r['compile_s']:>10.2f} {peak:>9.0f} "
            f"{mem.get('temp_bytes', 0) / 2**20:>9.1f}"
        )
    return "\n".join(lines)


def jobs(args: argparse.Namespace) -> list[tuple[str, str, str | None]]:
    """(phase, preset, phase-2 model or None) of every row, in output order."""
    out: list[tuple[str, str, str | None]] = []
    for phase in args.phase:
        for preset in args.preset:
            models = args.dyn_model if phase == "dyn" else [None]
            out += [(phase, preset, model) for model in models]
    return out


def job_argv(args: argparse.Namespace, phase: str, preset: str, model: str | None) -> list[str]:
    """The `nmjax bench` arguments that run exactly one row of `args`."""
    argv = ["--phase", phase, "--preset", preset, "--data", args.data]
    argv += ["--steps", str(args.steps), "--warmup", str(args.warmup)]
    for item in args.overrides:
        argv += ["--set", item]
    if args.compute_dtype is not None:
        argv += ["--compute-dtype", args.compute_dtype]
    if model is not None:
        argv += ["--dyn-model", model]
    if args.keypoints is not None:
        argv += ["--keypoints", str(args.keypoints)]
    return argv


def run_job(args: argparse.Namespace, phase: str, preset: str, model: str | None) -> dict:
    """One row, measured in this process."""
    cfg = configs(args, phase, preset)
    if phase == "skel":
        return bench_skel(cfg, preset, args.steps, args.warmup)
    k = args.keypoints or dataset_spec(args.data).num_keypoints
    cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, model=model))
    return bench_dyn(cfg, preset, k, args.steps, args.warmup)


def run_job_subprocess(
    args: argparse.Namespace, phase: str, preset: str, model: str | None
) -> tuple[dict[str, Any], dict[str, Any]]:
    """(environment, row) of one row measured in a fresh Python process, so that its peak memory
    is its own (the device's peak_bytes_in_use and the peak RSS only grow within a process)."""
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "row.json")
        argv = [*job_argv(args, phase, preset, model), "--same-process", "--out", out]
        cmd = [sys.executable, "-m", "nmjax.cli", "bench", *argv]
        done = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            lines = done.stderr.strip().splitlines() or [f"exit status {done.returncode}"]
            raise ValueError(f"row {phase}/{preset} failed: {lines[-1]}")
        with open(out) as f:
            result = json.load(f)
    return result["environment"], result["rows"][0]


def run(args: argparse.Namespace, emit: Callable[[str], None] = print) -> dict[str, Any]:
    """Runs every (phase, preset[, model]) row; returns {"environment": ..., "rows": [...]}.

    With more than one row each runs in its own process unless `args.same_process`; this process
    then never touches a device (on a GPU it would hold the memory the rows need), and the
    environment is the first row's.
    """
    todo = jobs(args)
    separate = not args.same_process and len(todo) > 1
    env: dict[str, Any] = {} if separate else environment()
    if env:
        emit(" ".join(f"{k}={v}" for k, v in env.items()))
    rows = []
    for job in todo:
        if separate:
            row_env, row = run_job_subprocess(args, *job)
            if not env:
                env = row_env
                emit(" ".join(f"{k}={v}" for k, v in env.items()))
        else:
            row = run_job(args, *job)
        rows.append(row)
        emit(format_table(rows[-1:]).splitlines()[-1])
    emit("")
    emit(format_table(rows))
    return {"environment": env, "args": vars(args), "rows": rows}


# --- the optimisations in the code vs their plain formulations --------------------------------


def plain_decoder(decoder: Any, maps: jax.Array, context: jax.Array) -> jax.Array:
    """`VoxelDecoder.__call__` with its input conv on the per-frame concatenation [g_t, context].

    Args:
      decoder: a `nmjax.models.detector.VoxelDecoder`.
      maps: (B, T, g, g, g, K); context: (B, g, g, g, C + K + 3).

    Returns:
      (B, T, G, G, G) raw logits, as `decoder(maps, context)`.
    """
    from flax import nnx

    from nmjax.models.blocks import LEAK, upsample_trilinear

    b, t = maps.shape[:2]
    w = decoder.inp.kernel[...][0, 0, 0]
    shared = jnp.broadcast_to(context[:, None], (b, t, *context.shape[1:]))
    x = nnx.leaky_relu(jnp.concatenate([maps, shared], -1) @ w + decoder.inp.bias[...], LEAK)
    x = x.reshape(b * t, *x.shape[2:])
    x = decoder.up1(upsample_trilinear(x) if decoder.upsample_first else x)
    raw = decoder.out(decoder.up2(upsample_trilinear(x)))[..., 0]
    return raw.reshape(b, t, *raw.shape[1:])


def fast_decoder(decoder: Any, maps: jax.Array, context: jax.Array) -> jax.Array:
    """The code's `VoxelDecoder.__call__` (frame-independent share of the input conv once)."""
    return decoder(maps, context)


def plain_decoder_input(maps: jax.Array, context: jax.Array, w: jax.Array) -> jax.Array:
    """The decoder's 1x1x1 input conv on [g_t, context] concatenated for every frame.

    Args:
      maps: (B, T, g, g, g, K); context: (B, g, g, g, C + K + 3); w: (2K + C + 3, C).

    Returns:
      (B, T, g, g, g, C) (no bias).
    """
    shared = jnp.broadcast_to(context[:, None], (*maps.shape[:2], *context.shape[1:]))
    return jnp.concatenate([maps, shared], -1) @ w


def fast_decoder_input(maps: jax.Array, context: jax.Array, w: jax.Array) -> jax.Array:
    """The same conv as `VoxelDecoder.__call__` computes it: the context share once per crop."""
    k = maps.shape[-1]
    return maps @ w[:k] + (context @ w[k:])[:, None]


def plain_conv3d(x: jax.Array, kernel: jax.Array) -> jax.Array:
    """XLA's native stride-1 'SAME' 3D convolution, x (B,X,Y,Z,Ci), kernel (k,k,k,Ci,Co)."""
    dims = ("NDHWC", "DHWIO", "NDHWC")
    return jax.lax.conv_general_dilated(x, kernel, (1, 1, 1), "SAME", dimension_numbers=dims)


def fast_conv3d(x: jax.Array, kernel: jax.Array) -> jax.Array:
    """`blocks.conv3d_same` in the form the code chooses on CPU (2D convolutions: taps stacked on
    the channels for thin inputs, one per tap otherwise), whatever the backend."""
    from nmjax.models import blocks

    return blocks.conv3d_same(x, kernel, blocks.cpu_conv_form(x.shape, kernel.shape[0]))


def plain_stem(voxels: jax.Array, kernel: jax.Array) -> jax.Array:
    """The FeatureNet stem conv on [occupancy, x, y, z] concatenated to every sample.

    Args:
      voxels: (B, G, G, G); kernel: (k, k, k, 1 + 3, Co).

    Returns:
      (B, G, G, G, Co) without bias.
    """
    from nmjax.keypoints import add_coord_channels
    from nmjax.models.blocks import conv3d_same

    return conv3d_same(add_coord_channels(voxels[..., None]), kernel, "native")


def fast_stem(voxels: jax.Array, kernel: jax.Array) -> jax.Array:
    """The FeatureNet stem as in the code: the occupancy convolved per sample, the coordinate
    channels' convolution in closed form once (`blocks.coord_conv3d_same`) and broadcast."""
    from nmjax.models.blocks import conv3d_same, coord_conv3d_same

    coords = coord_conv3d_same(kernel[..., 1:, :], voxels.shape[1])
    return conv3d_same(voxels[..., None], kernel[..., :1, :]) + coords


def plain_gaussian_maps(keypoints: jax.Array, sigma: float, n: int) -> jax.Array:
    """Dense Eq. 7 gaussian maps: alpha exp(-||x - mu||^2 / (2 (sigma/n)^2)) on the full grid.

    Args:
      keypoints: (..., K, 4); sigma: width in cells; n: cells per axis.

    Returns:
      (..., n, n, n, K), as `keypoints.gaussian_maps`.
    """
    from nmjax.keypoints import coord_grid

    grid = coord_grid(n)[..., None, :]  # (n, n, n, 1, 3)
    mu = keypoints[..., None, None, None, :, :3]  # (..., 1, 1, 1, K, 3)
    d2 = jnp.sum(jnp.square(grid - mu), axis=-1)  # (..., n, n, n, K)
    alpha = keypoints[..., None, None, None, :, 3]
    return alpha * jnp.exp(-d2 / (2 * (sigma / n) ** 2))


def fast_gaussian_maps(keypoints: jax.Array, sigma: float, n: int) -> jax.Array:
    """`keypoints.gaussian_maps` (separable: three 1-D profiles and an outer product)."""
    from nmjax.keypoints import gaussian_maps

    return gaussian_maps(keypoints, sigma, n)


@dataclasses.dataclass(frozen=True)
class Case:
    """One optimisation: plain and fast functions of the same float arguments (jittable)."""

    name: str
    shape: str
    plain: Callable[..., jax.Array]
    fast: Callable[..., jax.Array]
    args: tuple[Any, ...]
    applies: bool = True  # False: the code takes the plain path on this backend


def optimisation_cases(preset: str, data: str = "synth-arm", batch: int | None = None) -> list:
    """The cases (a)-(d) on the shapes of `skel_preset(data, preset)`; `batch` overrides B*T."""
    from flax import nnx

    from nmjax.models.detector import VoxelDecoder

    cfg = skel_preset(data, preset)
    m = cfg.model
    b, t = cfg.data.batch_size, cfg.data.frames
    if batch is not None:
        b, t = 1, batch
    bt, big, g, c, k = b * t, m.grid, m.grid // m.heatmap_stride, m.channels, m.num_keypoints
    c4, c2 = max(1, c // 4), max(1, c // 2)
    rng = np.random.default_rng(0)

    def normal(*shape: int, scale: float = 1.0) -> jax.Array:
        return jnp.asarray(rng.normal(scale=scale, size=shape), jnp.float32)

    voxels = jnp.asarray(rng.random((bt, big, big, big)) > 0.8, jnp.float32)
    keypoints = jnp.concatenate(
        [normal(b, t, k, 3, scale=0.4), jnp.asarray(rng.random((b, t, k, 1)), jnp.float32)], -1
    )
    decoder = VoxelDecoder(2 * k + c + 3, c, m.heatmap_stride, rngs=nnx.Rngs(0))
    graphdef, params = nnx.split(decoder)
    maps, context = normal(b, t, g, g, g, k), normal(b, g, g, g, c + k + 3)
    on_cpu = jax.default_backend() == "cpu"
    cases = [
        Case(
            "(a) decoder input conv once per crop",
            f"B={b} T={t} g={g} K={k} C={c}",
            lambda p, x, y: plain_decoder(nnx.merge(graphdef, p), x, y),
            lambda p, x, y: fast_decoder(nnx.merge(graphdef, p), x, y),
            (params, maps, context),
        ),
        Case(
            "(a) ... the input conv alone",
            f"B={b} T={t} g={g} K={k} C={c}",
            plain_decoder_input,
            fast_decoder_input,
            (maps, context, normal(2 * k + c + 3, c, scale=0.1)),
        ),
    ]
    for label, n, ci, co, ks in (
        ("stem occupancy", big, 1, c4, 5),
        ("decoder last", big, c4, c4, 3),
        ("decoder first at G", big, c2, c4, 3),
        ("feature res1", big // 2, c4, c2, 3),
    ):
        cases.append(
            Case(
                f"(b) sliced 3D conv: {label}",
                f"({bt},{n},{n},{n},{ci})->{co} k{ks}",
                plain_conv3d,
                fast_conv3d,
                (normal(bt, n, n, n, ci), normal(ks, ks, ks, ci, co, scale=0.1)),
                applies=on_cpu,
            )
        )
    cases.append(
        Case(
            "(c) stem coordinates convolved once",
            f"({bt},{big},{big},{big}) k5 ->{c4}",
            plain_stem,
            fast_stem,
            (voxels, normal(5, 5, 5, 4, c4, scale=0.1)),
        )
    )
    sigma = m.sigma_g
    cases.append(
        Case(
            "(d) separable gaussian maps",
            f"B={b} T={t} K={k} n={g}",
            lambda x: plain_gaussian_maps(x, sigma, g),
            lambda x: fast_gaussian_maps(x, sigma, g),
            (keypoints,),
        )
    )
    return cases


def forward_backward(fn: Callable[..., jax.Array], args: tuple[Any, ...]) -> Callable:
    """jit of ((sum(fn(*args) * r), fn(*args)), gradient of the sum w.r.t. every argument), with
    r a fixed random cotangent."""
    out = jax.eval_shape(fn, *args)
    cotangent = jnp.asarray(np.random.default_rng(1).normal(size=out.shape), jnp.float32)

    def loss(*a: Any) -> tuple[jax.Array, jax.Array]:
        y = fn(*a)
        return jnp.sum(y * cotangent), y

    grad_fn = jax.value_and_grad(loss, argnums=tuple(range(len(args))), has_aux=True)
    return jax.jit(grad_fn)


def time_compiled(fn: Callable, args: tuple[Any, ...], repeats: int) -> tuple[float, Any]:
    """(median seconds per call over `repeats` after one untimed call, the last result)."""
    compiled = fn.lower(*args).compile()
    result = jax.block_until_ready(compiled(*args))
    times = []
    for _ in range(repeats):
        tic = time.perf_counter()
        result = jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - tic)
    return float(np.median(times)), result


def run_case(case: Case, repeats: int) -> dict[str, Any]:
    """Forward + backward time of both forms, their ratio, and their largest output difference."""
    plain_s, ((plain_value, _), plain_grads) = time_compiled(
        forward_backward(case.plain, case.args), case.args, repeats
    )
    fast_s, ((fast_value, _), fast_grads) = time_compiled(
        forward_backward(case.fast, case.args), case.args, repeats
    )
    # Relative to the whole gradient: a leaf whose true gradient is ~0 (a conv bias followed by
    # GroupNorm) holds only rounding noise, and a per-leaf ratio would report that noise as O(1).
    pairs = list(zip(jax.tree.leaves(plain_grads), jax.tree.leaves(fast_grads), strict=True))
    diff_sq = sum(float(jnp.sum(jnp.square(a - b))) for a, b in pairs)
    norm_sq = sum(float(jnp.sum(jnp.square(a))) for a, _ in pairs)
    diff = (diff_sq / (norm_sq + 1e-24)) ** 0.5
    return {
        "name": case.name,
        "shape": case.shape,
        "plain_s": plain_s,
        "fast_s": fast_s,
        "speedup": plain_s / fast_s,
        "loss_rel_diff": float(abs(plain_value - fast_value) / (abs(plain_value) + 1e-12)),
        "grad_rel_diff": diff,
        "used_on_this_backend": case.applies,
    }


def bench_prefetch(cfg: Any, batches: int, prefetch: int = 2) -> dict[str, Any]:
    """(e) Phase-1 input pipeline with grain prefetch off (0) and on (`prefetch` batches).

    Each batch is followed by a stand-in device step (a sleep, which like device work leaves
    the host threads free) as long as the mean un-prefetched load time; "wait" is the time
    `next()` blocks. Without prefetch it is the whole load; with it, only the part not hidden
    behind the step.
    """
    from nmjax.data import pipeline

    def waits(data_cfg: Any, compute_s: float) -> list[float]:
        it = pipeline.skel_iterator(data_cfg, "train", seed=0)
        next(it)  # start-up (threads, file opening) not counted
        out = []
        for _ in range(batches):
            tic = time.perf_counter()
            next(it)
            out.append(time.perf_counter() - tic)
            time.sleep(compute_s)
        return out

    off = waits(dataclasses.replace(cfg.data, prefetch=0), 0.0)
    compute_s = float(np.mean(off))
    off = waits(dataclasses.replace(cfg.data, prefetch=0), compute_s)
    on = waits(dataclasses.replace(cfg.data, prefetch=prefetch), compute_s)
    plain_s, fast_s = float(np.mean(off)), float(np.mean(on))
    return {
        "name": f"(e) grain prefetch {prefetch} vs 0 (batch wait)",
        "shape": f"B={cfg.data.batch_size} T={cfg.data.frames} G={cfg.data.grid}",
        "plain_s": plain_s,
        "fast_s": fast_s,
        "speedup": plain_s / max(fast_s, 1e-9),
        "simulated_step_s": compute_s,
        "used_on_this_backend": True,
    }


def format_optimisations(rows: list[dict[str, Any]]) -> str:
    header = (
        f"{'optimisation':<48} {'shape':<32} {'plain s':>9} {'fast s':>9} {'speed-up':>8} "
        f"{'grad rel diff':>13}"
    )
    lines = [header, "-" * len(header)]
    for r in rows:
        note = "" if r["used_on_this_backend"] else "  (not used on this backend)"
        diff = f"{r['grad_rel_diff']:.1e}" if "grad_rel_diff" in r else "-"
        lines.append(
            f"{r['name']:<48} {r['shape']:<32} {r['plain_s']:>9.4f} {r['fast_s']:>9.4f} "
            f"{r['speedup']:>7.2f}x {diff:>13}{note}"
        )
    return "\n".join(lines)


def optimisations_main(argv: Sequence[str]) -> int:
    """experiments/bench_optimisations.py: every optimisation vs its plain form, one process."""
    from nmjax.data.synthetic import ensure_dataset

    parser = argparse.ArgumentParser(
        prog="bench_optimisations.py",
        description="Forward+backward time of each optimisation in the code vs its plain form.",
    )
    parser.add_argument("--preset", default="cpu", choices=PRESETS, help="chooses the shapes")
    parser.add_argument("--data", default="synth-arm")
    parser.add_argument("--batch", type=int, default=None, help="override B*T of the shapes")
    parser.add_argument("--repeats", type=int, default=3, help="timed calls per form (median)")
    parser.add_argument("--prefetch-batches", type=int, default=10, help="batches for (e)")
    parser.add_argument("--only", nargs="+", default=None, help="case letters, e.g. a b e")
    add_override_argument(parser, "phase-1 data overrides")
    parser.add_argument("--out", default=None, help="JSON output file")
    args = parser.parse_args(list(argv))
    env = environment()
    print(" ".join(f"{k}={v}" for k, v in env.items()))
    wanted = set(args.only or "abcde")
    rows = []
    try:
        for case in optimisation_cases(args.preset, args.data, args.batch):
            if case.name[1] in wanted:
                rows.append(run_case(case, args.repeats))
                print(format_optimisations(rows[-1:]).splitlines()[-1], flush=True)
        if "e" in wanted:
            cfg = apply_overrides(skel_preset(args.data, args.preset), args.overrides)
            ensure_dataset(cfg.data.name, cfg.data.root)  # generation not timed
            rows.append(bench_prefetch(cfg, args.prefetch_batches, max(cfg.data.prefetch, 1)))
    except (ValueError, FileNotFoundError) as err:
        print(f"bench_optimisations: {err}", file=sys.stderr)
        return 2
    print()
    print(format_optimisations(rows))
    if args.out is not None:
        atomic.write_json(args.out, {"environment": env, "args": vars(args), "rows": rows})
        print(f"wrote {args.out}")
    return 0
