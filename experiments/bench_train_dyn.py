"""Steps per second of the phase-2 train step (`nmjax.train.dyn.train_step`) on this machine.

Random-walk keypoint trajectories on a hand-like skeleton (five chains) stand in for a phase-1
run (the step's cost does not depend on the values). Prints one JSON line per (preset, model).

    JAX_PLATFORMS=cpu .venv/bin/python experiments/bench_train_dyn.py --keypoints 12 --steps 20
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from nmjax.config import dyn_preset
from nmjax.train import dyn


def bench(preset: str, model: str, num_keypoints: int, steps: int) -> dict[str, float | str]:
    cfg = dyn_preset("synth-arm", preset)
    cfg = dyn.dataclasses.replace(cfg, model=dyn.dataclasses.replace(cfg.model, model=model))
    # Hand-like tree: five chains from the root (depth about K/5, as in synth-hand).
    parents = tuple(max(k - 5, 0) for k in range(num_keypoints))
    order = tuple(range(num_keypoints))
    rng = np.random.default_rng(0)
    walk = np.cumsum(rng.normal(scale=0.01, size=(400, num_keypoints, 4)), axis=0)
    poses, starts = dyn.crop_table({"walk": walk.astype(np.float32)}, cfg.frames)
    poses, starts = jnp.asarray(poses), jnp.asarray(starts)
    graphdef, state = dyn.build(cfg, parents, order)
    step_fn = dyn.make_train_step(graphdef, cfg)
    key = jax.random.key(0)
    tic = time.perf_counter()
    state, metrics = step_fn(state, poses, starts, key, jnp.int32(0))
    jax.block_until_ready(metrics)
    compile_s = time.perf_counter() - tic
    tic = time.perf_counter()
    for i in range(1, steps + 1):
        state, metrics = step_fn(state, poses, starts, key, jnp.int32(i))
    jax.block_until_ready(metrics)
    elapsed = time.perf_counter() - tic
    return {
        "preset": preset,
        "model": model,
        "K": num_keypoints,
        "depth": max(k // 5 + (k % 5 > 0) for k in range(num_keypoints)),
        "T": cfg.frames,
        "B": cfg.batch_size,
        "S": cfg.model.posterior_samples,
        "D_z": cfg.model.latent,
        "D_h": cfg.model.hidden,
        "first_call_s": round(compile_s, 2),
        "steps_per_s": round(steps / elapsed, 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keypoints", type=int, default=12)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--presets", nargs="+", default=["cpu", "default"])
    parser.add_argument("--models", nargs="+", default=["nm", "vrnn"])
    args = parser.parse_args()
    print(json.dumps({"devices": str(jax.devices()), "load_avg_1min": os.getloadavg()[0]}))
    for preset in args.presets:
        for model in args.models:
            print(json.dumps(bench(preset, model, args.keypoints, args.steps)), flush=True)


if __name__ == "__main__":
    main()
