"""Benchmarks of the train steps (`nmjax bench`): step timing and memory.

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
  from the root) stand in for a phase-1 run; the step's cost does not depend on the values.
  "load" is cutting the step's drawn crops from the table on the host.
- Detect: the phase-1 preset's (untrained) detector on phase-2 crops of `--data` (T of the phase-2
  preset, B of the phase-1 preset per call), forward only, as `dyn_inputs.DetectedCrops` runs
  it: "load" normalises and voxelises the crops (`dyn_inputs.clip_voxels`), "compute" is the
  compiled detector. Its frames/s sits beside the phase-1 step's (forward and backward).

Compile time is `jit(...).lower(...).compile()`, timed on its own; the compiled executable is then
the one that runs. Memory: the compiled step's `memory_analysis()` (argument, output, temporary
bytes) and the device's `memory_stats()["peak_bytes_in_use"]` where it reports one (GPU), else the
process's peak resident set size (`resource.getrusage`). Both only grow within a process, so with
several rows each row is measured in a fresh process (`--same-process` to opt out). The JSON of
`--out` opens with the provenance stamp (`nmjax.provenance`: commit, CPU model, GPU, versions and
`METRICS`, the definitions of the columns).

The convolution forms are compared through the configuration (`--set skel:model.conv_form=native`
against the default "auto"; the row records the field); the optimisations in the kernels
(`nmjax.models.conv_kernels`), each timed against its plain formulation, are
experiments/bench_optimisations.py's.
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

from nmjax.config import dataset_spec, dyn_preset, skel_preset
from nmjax.config_io import apply_overrides

# "detect": the frozen detector on phase-2 crops (forward only), beside the two train steps.
PHASES = ("skel", "dyn", "detect")
MEMORY_KEYS = ("argument_bytes", "output_bytes", "temp_bytes")
# What each row reports, recorded in every results file (`nmjax.provenance`).
METRICS = {
    "steps_per_s": "timed steps / (load + compute seconds): the rate a training run sees",
    "frames_per_s": "steps_per_s x B x T: training frames consumed per second",
    "load_s_per_step": "phase 1: wait for the next grain batch plus host -> device placement, "
    "blocked until ready; phase 2: cutting the drawn crops on the host; detect: normalising and "
    "voxelising the crops (`dyn_inputs.clip_voxels`)",
    "compute_s_per_step": "the compiled step until its outputs are ready, mean over the timed "
    "steps (compute_s_median: their median)",
    "compile_s": "jit(step).lower(...).compile(), timed on its own; the executable then runs",
    "memory": "memory_analysis() argument / output / temp bytes of the compiled step; "
    "peak_bytes_in_use of the device where it reports one (GPU), else the process's peak RSS",
}


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


def print_and_save(
    table: str, out: str | None, env: dict, args: Any, rows: list, stamp: dict
) -> None:
    """Prints a benchmark's table; with `out`, writes {"provenance": `stamp`, "environment",
    "args", "rows"} there."""
    from nmjax import provenance

    print()
    print(table)
    if out is not None:
        provenance.write_json(out, {"environment": env, "args": vars(args), "rows": rows}, stamp)
        print(f"wrote {out}")


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


def check_batch(cfg: Any, phase: str, mesh: Any) -> None:
    """Refuses a batch of `cfg` (either phase) that does not split over the mesh's devices,
    naming the `--set` item of `phase` that changes it."""
    from nmjax.train import parallel

    parallel.check_batch_size(
        cfg.data.batch_size, "data.batch_size", mesh, f"--set {phase}:data.batch_size="
    )


# --- phase 1 ----------------------------------------------------------------------------------


def bench_skel(cfg: Any, preset: str, steps: int, warmup: int) -> dict[str, Any]:
    """Times the phase-1 train step of `cfg` (a SkelTrainConfig) on its real data pipeline."""
    from nmjax.data import pipeline
    from nmjax.data.synthetic import ensure_dataset
    from nmjax.train import parallel, skel

    skel.check_config(cfg)
    ensure_dataset(cfg.data.name, cfg.data.root)  # a synthetic set is generated here, untimed
    mesh = parallel.data_mesh()
    check_batch(cfg, "skel", mesh)
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
        "conv_form": m.conv_form,
    }
    note = (
        f"grain pipeline (prefetch={cfg.data.prefetch}, workers={cfg.data.worker_count}); "
        "load = wait for the batch + host->device placement"
    )
    return _row("skel", preset, shape, load, compute, compile_s, memory_of(compiled), note)


# --- phase 2 ----------------------------------------------------------------------------------


# Timed steps (after 2 warm-up steps) behind a budget in minutes (`train-skel --fit-minutes`,
# `nmjax rig --minutes`): enough for a steady median.
FIT_TIMED_STEPS = 5


def fit_to_minutes(cfg: Any, minutes: float, started: float) -> tuple[Any, float]:
    """`cfg` (a SkelTrainConfig) with as many steps as fit `minutes` of wall time counted from
    `started` (time.perf_counter), the step timed here first (`bench_skel`, on the run's data)
    and the schedule scaled with the steps (`config.fit_schedule`).

    Returns:
      (the fitted configuration, the measured seconds per step).

    Raises:
      ValueError: several processes (each would read its own clock), or too few minutes.
    """
    from nmjax.config import fit_schedule

    if jax.process_count() > 1:
        raise ValueError("a budget in minutes works in single-process runs only; set steps instead")
    row = bench_skel(cfg, "fit", steps=FIT_TIMED_STEPS, warmup=2)
    per_step = row["compute_s_median"] + row["load_s_per_step"]
    return fit_schedule(cfg, per_step, minutes, time.perf_counter() - started), per_step


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
    from nmjax.train import dyn, dyn_inputs, parallel

    mesh = parallel.data_mesh()
    check_batch(cfg, "dyn", mesh)
    b, t = cfg.data.batch_size, cfg.data.frames
    parents, order = hand_tree(num_keypoints)
    table = dyn_inputs.CropTable(*dyn_inputs.crop_table({"walk": random_walk(num_keypoints)}, t), t)
    draws = dyn.CropDraws(jax.random.key(cfg.seed), table.num_starts, b)
    key = parallel.replicate(jax.random.key(cfg.seed), mesh)
    graphdef, state = dyn.build(cfg, parents, order)
    state = parallel.replicate(state, mesh)
    settings = dyn.StepSettings.of(cfg)
    compiled, compile_s = _timed_compile(
        dyn.train_step,
        state,
        parallel.global_array(table.batch(draws.at(0)), mesh),
        key,
        jnp.int32(0),
        graphdef=graphdef,
        settings=settings,
        mesh=mesh,
    )
    load, compute = [], []
    for i in range(warmup + steps):
        tic = time.perf_counter()
        x = parallel.global_array(table.batch(draws.at(i)), mesh)
        loaded = time.perf_counter()
        state, metrics = jax.block_until_ready(compiled(state, x, key, jnp.int32(i)))
        if i >= warmup:
            load.append(loaded - tic)
            compute.append(time.perf_counter() - loaded)
    if not np.isfinite(float(metrics["loss"])):
        raise RuntimeError(f"bench: phase-2 loss became {float(metrics['loss'])}")
    m = cfg.model
    shape = {
        "model": m.model,
        "B": b,
        "T": t,
        "K": num_keypoints,
        "S": m.posterior_samples,
        "D_z": m.latent,
        "D_h": m.hidden,
        "compute_dtype": "float32",
    }
    note = "crops cut from a table on the host, the draws computed a block of steps at a time"
    return _row("dyn", preset, shape, load, compute, compile_s, memory_of(compiled), note)


# --- phase-2 crop detection -------------------------------------------------------------------


def bench_detect(cfg: Any, preset: str, frames: int, steps: int, warmup: int) -> dict[str, Any]:
    """Times the detector on phase-2 crops of `frames` frames (`cfg` a SkelTrainConfig)."""
    from flax import nnx

    from nmjax.data.datasets import load_sequences
    from nmjax.data.synthetic import ensure_dataset
    from nmjax.train import dyn_inputs, skel, trained

    skel.check_config(cfg)
    root = ensure_dataset(cfg.data.name, cfg.data.root)  # generated here, untimed
    rate, b = cfg.data.sample_rate, cfg.data.batch_size
    clips = [
        (seq, int(t))
        for seq in load_sequences(cfg.data.name, "train", root)
        for t in dyn_inputs.crop_starts(seq.num_frames, frames, rate)
    ]
    graphdef, state = skel.build(cfg)
    detector = trained.Detector.of(nnx.merge(graphdef, state["model"]), cfg, "bench")

    def voxels(i: int) -> jax.Array:
        part = [clips[(i * b + j) % len(clips)] for j in range(b)]
        return jnp.asarray(
            np.stack([dyn_inputs.clip_voxels(s, t, frames, cfg.data) for s, t in part])
        )

    compiled, compile_s = _timed_compile(
        trained.detect_batch, detector.graphdef, detector.state, voxels(0)
    )
    load, compute = [], []
    for i in range(warmup + steps):
        tic = time.perf_counter()
        batch = jax.block_until_ready(voxels(i))
        toc = time.perf_counter()
        keypoints = jax.block_until_ready(compiled(detector.state, batch))
        if i >= warmup:
            load.append(toc - tic)
            compute.append(time.perf_counter() - toc)
    if not np.all(np.isfinite(np.asarray(keypoints))):
        raise RuntimeError("bench: the detector's keypoints are not finite")
    m = cfg.model
    shape = {
        "data_name": cfg.data.name,
        "B": b,
        "T": frames,
        "G": m.grid,
        "C": m.channels,
        "K": m.num_keypoints,
        "compute_dtype": m.compute_dtype,
        "conv_form": m.conv_form,
    }
    note = "phase-2 crops, each normalised on its own; load = clip_voxels on the host"
    return _row("detect", preset, shape, load, compute, compile_s, memory_of(compiled), note)


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
    """The preset's config of `phase` with the --set overrides, --compute-dtype and --dyn-model
    ("detect" runs the phase-1 preset's detector and takes the skel: overrides)."""
    if phase in ("skel", "detect"):
        cfg = skel_preset(args.data, preset)
        if args.compute_dtype is not None:
            model = dataclasses.replace(cfg.model, compute_dtype=args.compute_dtype)
            cfg = dataclasses.replace(cfg, model=model)
    else:
        cfg = dyn_preset(args.data, preset)
    return apply_overrides(
        cfg, _split_overrides(args.overrides, "skel" if phase == "detect" else phase)
    )


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
        label = r["preset"] if r["phase"] != "dyn" else f"{r['preset']}/{r['model']}"
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
    if phase == "detect":
        frames = dyn_preset(args.data, preset).data.frames
        return bench_detect(cfg, preset, frames, args.steps, args.warmup)
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
    """Runs every (phase, preset[, model]) row; returns {"provenance": `nmjax.provenance.stamp`
    with `METRICS`, "environment": ..., "args": ..., "rows": [...]}.

    With more than one row each runs in its own process unless `args.same_process`; this process
    then never touches a device (on a GPU it would hold the memory the rows need), and the
    environment is the first row's.
    """
    from nmjax import provenance

    stamp = provenance.stamp(METRICS)
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
    return {"provenance": stamp, "environment": env, "args": vars(args), "rows": rows}
