"""Each optimisation in the model against its plain formulation, forward + backward, one process.

(a) decoder input conv once per crop, (b) sliced CPU 3D convolution vs XLA's, (c) the CoordConv
stem convolving the coordinate channels once, (d) separable gaussian maps, (e) grain prefetch,
(f) the stem in 2x2x2 blocks on the G/2 grid, then the first pool, (g) each convolution after a
trilinear upsampling evaluated on the coarse grid.

The fast form of every case is the model's own code (`VoxelDecoder`, `Conv3D` and its kernels in
`nmjax.models.conv_kernels`, the stem and first pool of `FeatureNet`, an upsampling
`ConvNormAct`, `keypoints.gaussian_maps`, the grain pipeline), its layers built with the form
each case measures (`conv_kernels.Evaluation`); the plain forms are the library's reference
(`nmjax.models.reference`), where `tests/test_plain_forms.py` checks that both compute the same
function. Each row also reports their relative output and gradient differences at the timed
shapes.

    JAX_PLATFORMS=cpu .venv/bin/python experiments/bench_optimisations.py --preset cpu \
        --out experiments/results/bench_optimisations_cpu.json
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from nmjax import keypoints as kp_lib
from nmjax import provenance
from nmjax.bench import environment, print_and_save
from nmjax.config import PRESETS, skel_preset
from nmjax.config_io import add_override_argument, apply_overrides
from nmjax.models import blocks, conv_kernels, reference
from nmjax.models.conv_kernels import Evaluation
from nmjax.models.detector import VoxelDecoder

METRICS = {
    "plain_s, fast_s": "median seconds of --repeats jitted forward + backward calls (value and "
    "gradient with respect to every input and parameter) of the plain and the optimised form; "
    "case (e): mean seconds next() blocks per batch behind a stand-in device step",
    "speedup": "plain_s / fast_s",
    "grad_rel_diff": "||g_plain - g_fast|| / ||g_plain|| over all inputs and parameters",
}


@dataclasses.dataclass(frozen=True)
class Case:
    """One optimisation: plain and fast functions of the same float arguments (jittable)."""

    name: str
    shape: str
    plain: Callable[..., jax.Array]
    fast: Callable[..., jax.Array]
    args: tuple[Any, ...]
    applies: bool = True  # False: the code takes the plain path on this backend


def module_case(
    name: str,
    shape: str,
    module: nnx.Module,
    plain: Callable[..., jax.Array],
    fast: Callable[..., jax.Array],
    *inputs: jax.Array,
    applies: bool = True,
) -> Case:
    """A case on a real module: both forms take its state (differentiated too), then `inputs`."""
    graphdef, state = nnx.split(module)
    return Case(
        name,
        shape,
        lambda s, *x: plain(nnx.merge(graphdef, s), *x),
        lambda s, *x: fast(nnx.merge(graphdef, s), *x),
        (state, *inputs),
        applies,
    )


def stem(net: blocks.FeatureNet, voxels: jax.Array) -> jax.Array:
    """The CoordConv stem's convolution (with its bias) of `net`: (B, G, G, G) -> (B, G, G, G,
    C/4)."""
    return net.stem.conv(voxels[..., None])


def stem_pool(net: blocks.FeatureNet, voxels: jax.Array) -> jax.Array:
    """The stem (conv5 + GroupNorm + LeakyReLU) and the first pool of `net`."""
    return net.pool1(net.stem(voxels[..., None]))


def optimisation_cases(preset: str, data: str = "synth-arm", batch: int | None = None) -> list:
    """The cases (a)-(d), (f), (g) on the shapes of `skel_preset(data, preset)`; `batch`
    overrides B*T."""
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

    decoder = VoxelDecoder(2 * k + c + 3, c, m.heatmap_stride, rngs=nnx.Rngs(0))
    maps, context = normal(b, t, g, g, g, k), normal(b, g, g, g, c + k + 3)
    shape = f"B={b} T={t} g={g} K={k} C={c}"
    # (b), (f), (g) are the CPU forms: measured in them whatever the backend, marked as not used
    # where "auto" takes XLA's native convolution.
    cpu_forms_used = conv_kernels.resolve("auto", None, (big,) * 3, 3, jnp.float32) != "native"
    cpu_form = Evaluation(conv_kernels.CPU_CONV_FORM)
    cases = [
        module_case(
            "(a, g) whole decoder: input conv once per crop, upsampled convs coarse",
            shape,
            decoder,
            reference.decoder,
            VoxelDecoder.__call__,
            maps,
            context,
        ),
        module_case(
            "(a) ... the input conv alone",
            shape,
            decoder,
            reference.decoder_input,
            VoxelDecoder.input_features,
            maps,
            context,
        ),
    ]
    for label, n, ci, co, ks in (
        ("stem occupancy", big, 1, c4, 5),
        ("decoder last", big, c4, c4, 3),
        ("decoder first at G", big, c2, c4, 3),
        ("feature res1", big // 2, c4, c2, 3),
    ):
        conv = blocks.Conv3D(ci, co, ks, evaluation=cpu_form, rngs=nnx.Rngs(0))
        cases.append(
            module_case(
                f"(b) sliced 3D conv: {label}",
                f"({bt},{n},{n},{n},{ci})->{co} k{ks}",
                conv,
                reference.conv3d,
                blocks.Conv3D.__call__,
                normal(bt, n, n, n, ci),
                applies=cpu_forms_used,
            )
        )
    voxels = jnp.asarray(rng.random((bt, big, big, big)) > 0.8, jnp.float32)
    stem_shape = f"({bt},{big},{big},{big}) k5 ->{c4}"
    # (c) alone: the occupancy by XLA's convolution in both forms, only the coordinates differ.
    net = blocks.FeatureNet(
        c,
        m.hourglass_channels,
        big,
        m.heatmap_stride,
        evaluation=Evaluation("native"),
        rngs=nnx.Rngs(0),
    )
    cases.append(
        module_case(
            "(c) stem coordinates convolved once",
            stem_shape,
            net,
            reference.stem_conv,
            stem,
            voxels,
        )
    )
    net = blocks.FeatureNet(
        c, m.hourglass_channels, big, m.heatmap_stride, evaluation=cpu_form, rngs=nnx.Rngs(0)
    )
    cases.append(
        module_case(
            "(f) stem in 2x2x2 blocks, first pool",
            f"{stem_shape}, pool",
            net,
            reference.stem_and_pool,
            stem_pool,
            voxels,
            applies=cpu_forms_used,
        )
    )
    # The coarse convs in their CPU form.
    coarse = VoxelDecoder(2 * k + c + 3, c, m.heatmap_stride, evaluation=cpu_form, rngs=nnx.Rngs(0))
    stages = [("decoder last upsampling", coarse.up2.layers[0], big // 2, c2)]
    if coarse.upsample_first:
        stages.insert(0, ("decoder first upsampling", coarse.up1.layers[0], g, c))
    for label, block, n, ci in stages:
        cases.append(
            module_case(
                f"(g) conv after upsampling, coarse: {label}",
                f"({bt},{n},{n},{n},{ci}) -> x2 -> {block.conv.kernel.shape[-1]} k3",
                block,
                reference.conv_after_upsampling,
                blocks.ConvNormAct.__call__,
                normal(bt, n, n, n, ci),
                applies=cpu_forms_used,
            )
        )
    keypoints = jnp.concatenate(
        [normal(b, t, k, 3, scale=0.4), jnp.asarray(rng.random((b, t, k, 1)), jnp.float32)], -1
    )
    sigma = m.sigma_g
    cases.append(
        Case(
            "(d) separable gaussian maps",
            f"B={b} T={t} K={k} n={g}",
            lambda x: reference.gaussian_maps(x, sigma, g),
            lambda x: kp_lib.gaussian_maps(x, sigma, g),
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
    """Forward + backward time of both forms, their ratio, and the relative difference of their
    outputs and of their gradients."""
    plain_s, ((_, plain_out), plain_grads) = time_compiled(
        forward_backward(case.plain, case.args), case.args, repeats
    )
    fast_s, ((_, fast_out), fast_grads) = time_compiled(
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
        # Over the whole output: the random-weighted sum the gradients are taken of can cancel
        # to near 0, and its relative difference then reports rounding noise as large.
        "value_rel_diff": float(
            jnp.linalg.norm(plain_out - fast_out) / (jnp.linalg.norm(plain_out) + 1e-12)
        ),
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


def main(argv: Sequence[str]) -> int:
    """Every optimisation vs its plain form, in this process; 2 on a bad dataset or override."""
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
    stamp = provenance.stamp(METRICS)
    env = environment()
    print(" ".join(f"{k}={v}" for k, v in env.items()))
    wanted = set(args.only or "abcdefg")
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
    print_and_save(format_optimisations(rows), args.out, env, args, rows, stamp)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
