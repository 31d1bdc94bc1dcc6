"""Memory of the phase-1 train step without running it: compile only, report memory_analysis().

    JAX_PLATFORMS=cpu .venv/bin/python experiments/step_memory.py --preset default \
        --data synth-hand --conv auto per_tap stacked native

For each 3D-convolution form, the compiled step's temporary / argument / output bytes at the
preset's shapes (B, T and anything else through --set), e.g. the paper's B=3, T=10, G=64, C=128,
K=28, whose step needs more memory than a development machine has. `--conv` sets model.conv_form,
how `conv_kernels.conv3d_same` evaluates stride-1 convolutions:

- auto: the code's choice (`conv_kernels.resolve`: on CPU "winograd", stacked taps where it does
  not apply);
- per_tap: one 2D convolution per depth tap (k shifted inputs, k kernel gradients);
- stacked: the k depth taps stacked on the channel axis, one 2D convolution;
- winograd: F(4x4x4, 3x3x3) for every float32 3x3x3 kernel, stacked taps for the others;
- native: XLA's 3D convolution everywhere (what GPU and TPU backends always use).

Also XLA's operation count of the compiled step (`cost_analysis()["flops"]`), which does not
depend on the machine's load. Writes nothing; prints one line per form (add --out FILE.json for
the numbers).
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
from flax import nnx

from nmjax import provenance
from nmjax.bench import environment
from nmjax.config import PRESETS, skel_preset
from nmjax.config_io import add_override_argument, apply_overrides
from nmjax.models import conv_kernels
from nmjax.models.detector import KeypointDetector
from nmjax.train import optim, parallel, skel

FORMS = conv_kernels.CONV_FORMS
METRICS = {
    "temp_bytes": "memory_analysis() temporary bytes of the compiled phase-1 train step "
    "(activations kept for the backward pass and scratch), compiled, never run",
    "argument_bytes, output_bytes": "memory_analysis() bytes of its arguments and outputs",
    "compile_s": "seconds to lower and compile the step",
    "flops": "XLA's operation count of the compiled step (cost_analysis), independent of load",
}


def step_memory(cfg, form: str) -> dict:
    """Compile time and memory_analysis() bytes of the phase-1 train step of `cfg`, every
    stride-1 convolution in `form` (model.conv_form)."""
    cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, conv_form=form))
    skel.check_config(cfg)
    model = KeypointDetector(cfg.model, rngs=nnx.Rngs(cfg.seed))
    settings, mesh = skel.StepSettings.of(cfg), parallel.data_mesh()
    graphdef, state = optim.init_state(model, settings.optimizer)
    g = cfg.model.grid
    voxels = jax.ShapeDtypeStruct((cfg.data.batch_size, cfg.data.frames, g, g, g), jnp.float32)
    tic = time.perf_counter()
    lowered = skel.train_step.lower(
        state, {"voxels": voxels}, graphdef=graphdef, settings=settings, mesh=mesh
    )
    compiled = lowered.compile()
    seconds = time.perf_counter() - tic
    analysis = compiled.memory_analysis()
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, list) else cost  # one dict per device in older jax
    return {
        "conv": form,
        "B": cfg.data.batch_size,
        "T": cfg.data.frames,
        "G": g,
        "C": cfg.model.channels,
        "K": cfg.model.num_keypoints,
        "compute_dtype": cfg.model.compute_dtype,
        "compile_s": seconds,
        "temp_bytes": int(analysis.temp_size_in_bytes),
        "argument_bytes": int(analysis.argument_size_in_bytes),
        "output_bytes": int(analysis.output_size_in_bytes),
        # XLA's operation count of the compiled step: independent of the machine's load, so two
        # networks' costs compare on a busy machine too.
        "flops": float(cost.get("flops", float("nan"))),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="default", choices=PRESETS)
    parser.add_argument("--data", default="synth-hand")
    parser.add_argument("--conv", nargs="+", default=list(FORMS), choices=FORMS)
    add_override_argument(parser, "config override, e.g. data.batch_size=1")
    parser.add_argument("--out", default=None, help="write the rows as JSON here")
    args = parser.parse_args()
    cfg = apply_overrides(skel_preset(args.data, args.preset), args.overrides)
    stamp = provenance.stamp(METRICS)
    env = environment()
    print(" ".join(f"{k}={v}" for k, v in env.items()))
    rows = []
    for form in args.conv:
        row = step_memory(cfg, form)
        rows.append(row)
        print(
            f"conv={form:<8} B={row['B']} T={row['T']} G={row['G']} C={row['C']} K={row['K']} "
            f"temp {row['temp_bytes']:,} bytes ({row['temp_bytes'] / 2**30:.2f} GiB), "
            f"arguments {row['argument_bytes'] / 2**30:.2f} GiB, outputs "
            f"{row['output_bytes'] / 2**30:.2f} GiB, {row['flops'] / 1e9:.1f} GFLOP, "
            f"compiled in {row['compile_s']:.0f} s",
            flush=True,
        )
    if args.out is not None:
        provenance.write_json(
            args.out, {"environment": env, "args": vars(args), "rows": rows}, stamp
        )
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
