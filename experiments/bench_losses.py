"""Microseconds per call of every loss term at the paper's shapes, jit (warm) vs plain NumPy.

Shapes: G=64, g=16, K=28, B=3, T=10, N=2 (Table 3, HanCo K). Prints a markdown table; also the
compiled memory footprint of volume_fitting forward + gradient. `--memory-only` runs just that
forward + gradient (for `/usr/bin/time -v` max RSS). The table is followed by the commit,
machine and column definitions (`nmjax.provenance`).

    JAX_PLATFORMS=cpu .venv/bin/python experiments/bench_losses.py
    JAX_PLATFORMS=cpu /usr/bin/time -v .venv/bin/python experiments/bench_losses.py --memory-only
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from nmjax import losses, provenance
from nmjax.config import LossWeights

G, GH, K, B, T, N = 64, 16, 28, 3, 10, 2
METRICS = {
    "jit (us/call)": "median microseconds of a warm jitted call within --budget seconds",
    "NumPy (us/call)": "the same for the plain NumPy formulation in this script",
    "max rel. diff": "max |jit - NumPy| over the output / max |NumPy|",
}
SEP_SIGMA = 0.02


def make_inputs(seed: int = 0, memory_only: bool = False) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    # A ball of occupied voxels (~1/8 of the grid), shifted per frame, like a moving body.
    x = np.linspace(-1, 1, G, dtype=np.float32)
    grid = np.stack(np.meshgrid(x, x, x, indexing="ij"), -1)
    centres = rng.uniform(-0.2, 0.2, (B, T, 3)).astype(np.float32)
    voxels = np.stack(
        [np.linalg.norm(grid - c, axis=-1) < 0.6 for c in centres.reshape(-1, 3)]
    ).reshape(B, T, G, G, G)
    kp = np.concatenate(
        [rng.uniform(-0.6, 0.6, (B, T, K, 3)), rng.uniform(0, 1, (B, T, K, 1))], -1
    ).astype(np.float32)
    if memory_only:
        return {"voxels": voxels.astype(np.float32), "keypoints": kp}
    return {
        "voxels": voxels.astype(np.float32),
        "recon": rng.uniform(0.01, 0.99, (B, T, G, G, G)).astype(np.float32),
        "heatmaps": rng.random((B, T, GH, GH, GH, K)).astype(np.float32),
        "keypoints": kp,
        "params": rng.normal(size=(N, K, K - 1)).astype(np.float32),
    }


# --- straightforward NumPy versions of the same formulas ---------------------------------------


def np_affinity(p):
    e = np.exp(p - p.max(-1, keepdims=True))
    soft = e / e.sum(-1, keepdims=True)
    a = np.zeros((*p.shape[:-1], p.shape[-2]), np.float32)
    for i in range(p.shape[-2]):
        a[..., i, np.arange(p.shape[-2]) != i] = soft[..., i, :]
    return a


def np_bce(v, r):
    r = np.clip(r, 1e-7, 1 - 1e-7)
    return -(v * np.log(r) + (1 - v) * np.log1p(-r)).mean((-3, -2, -1))


def np_sparsity(h):
    return np.abs(h.mean((-4, -3, -2))).mean(-1)


def np_pair(mu):
    return ((mu[..., :, None, :] - mu[..., None, :, :]) ** 2).sum(-1)


def np_separation(kp):
    mu = kp[..., :3]
    s = mu - mu.mean(-3, keepdims=True)
    e = np.exp(-np_pair(s).mean(-3) / (2 * SEP_SIGMA**2))
    k = kp.shape[-2]
    return (e * (1 - np.eye(k))).sum((-2, -1)) / (k * (k - 1))


def np_volume(v, kp):
    x = np.linspace(-1, 1, G, dtype=np.float32)
    pts = np.stack(np.meshgrid(x, x, x, indexing="ij"), -1).reshape(-1, 3)
    out = np.zeros(v.shape[:2], np.float32)
    for b in range(v.shape[0]):
        for t in range(v.shape[1]):
            occ = pts[v[b, t].reshape(-1) > 0]
            d = ((occ[:, None] - kp[b, t, None, :, :3]) ** 2).sum(-1).min(1)
            out[b, t] = d.mean() if len(d) else 0.0
    return out


def np_local(kp, a):
    return (a.max(0) * np_pair(kp[..., :3])).mean((-2, -1))


def np_time(kp, a):
    dist = np_pair(kp[..., :3])
    return (a.max(0) * np.abs(dist - dist.mean(-3, keepdims=True))).mean((-2, -1))


def np_complexity(a):
    total = 0.0
    for i in range(a.shape[0]):
        for j in range(a.shape[0]):
            if i != j:
                total = total + ((a[i] * a[j]) ** 2).mean()
    return total


def np_trajectory(kp, a):
    mu = kp[..., :3]
    vel = np.diff(mu, axis=-3)
    acc = np.diff(vel, axis=-3)

    def cos(u):
        un = u / np.maximum(np.linalg.norm(u, axis=-1, keepdims=True), 1e-6)
        return np.einsum("...kd,...ld->...kl", un, un).reshape(-1, K, K).mean(0)

    return (a.max(0) * (1.0 - (cos(vel) + cos(acc)) / 2)).mean()


# --- timing ------------------------------------------------------------------------------------


def time_call(fn: Callable[[], object], budget_s: float = 1.0, max_calls: int = 200) -> float:
    """Median microseconds of `fn()` (already warm), within a time budget."""
    times = []
    start = time.perf_counter()
    while len(times) < 3 or (time.perf_counter() - start < budget_s and len(times) < max_calls):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return float(np.median(times)) * 1e6


def vol_value_and_grad():
    return jax.jit(
        jax.value_and_grad(lambda v, kp: jnp.mean(losses.volume_fitting(v, kp)), argnums=1)
    )


def memory_report(inputs) -> str:
    fn = vol_value_and_grad()
    compiled = fn.lower(inputs["voxels"], inputs["keypoints"]).compile()
    stats = compiled.memory_analysis()
    mib = 2.0**20
    if stats is None:
        return "memory_analysis unavailable on this backend"
    return (
        f"volume_fitting fwd+grad (compiled): arguments {stats.argument_size_in_bytes / mib:.1f} "
        f"MiB, temporaries {stats.temp_size_in_bytes / mib:.1f} MiB, outputs "
        f"{stats.output_size_in_bytes / mib:.2f} MiB"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--memory-only", action="store_true")
    parser.add_argument("--budget", type=float, default=1.0, help="seconds of timing per entry")
    args = parser.parse_args()
    stamp = provenance.stamp(METRICS)
    inputs = make_inputs(memory_only=args.memory_only)
    dev = {k: jnp.asarray(v) for k, v in inputs.items()}
    if args.memory_only:
        value, grad = vol_value_and_grad()(dev["voxels"], dev["keypoints"])
        print(
            f"volume_fitting fwd+grad at G={G} K={K} B={B} T={T}: {float(value):.5f}, "
            f"|grad| {float(jnp.linalg.norm(grad)):.5f}"
        )
        print(memory_report(dev))
        return

    a_np = np_affinity(inputs["params"])
    a = losses.affinity_from_params(dev["params"])
    kp_np, v_np = inputs["keypoints"], inputs["voxels"]
    v, kp = dev["voxels"], dev["keypoints"]
    # (name, Eq., JAX function, its array arguments, NumPy function, its arguments). The arrays
    # are passed as jit arguments (not closed over) so XLA cannot constant-fold the result.
    cases = [
        (
            "reconstruction_bce",
            9,
            losses.reconstruction_bce,
            (v, dev["recon"]),
            np_bce,
            (v_np, inputs["recon"]),
        ),
        (
            "heatmap_sparsity",
            10,
            losses.heatmap_sparsity,
            (dev["heatmaps"],),
            np_sparsity,
            (inputs["heatmaps"],),
        ),
        (
            "separation",
            11,
            lambda x: losses.separation(x, SEP_SIGMA),
            (kp,),
            np_separation,
            (kp_np,),
        ),
        ("volume_fitting", 8, losses.volume_fitting, (v, kp), np_volume, (v_np, kp_np)),
        (
            "affinity_from_params",
            12,
            losses.affinity_from_params,
            (dev["params"],),
            np_affinity,
            (inputs["params"],),
        ),
        ("graph_local", 15, losses.graph_local, (kp, a), np_local, (kp_np, a_np)),
        ("graph_time", 16, losses.graph_time, (kp, a), np_time, (kp_np, a_np)),
        ("graph_complexity", 17, losses.graph_complexity, (a,), np_complexity, (a_np,)),
        ("graph_trajectory", 13, losses.graph_trajectory, (kp, a), np_trajectory, (kp_np, a_np)),
    ]
    rows = []
    for name, eq, jax_fn, jax_args, np_fn, np_args in cases:
        jitted = jax.jit(jax_fn)
        got = np.asarray(jax.block_until_ready(jitted(*jax_args)))  # compile + warm
        want = np.asarray(np_fn(*np_args))
        err = float(np.max(np.abs(got - want)) / (np.max(np.abs(want)) + 1e-12))
        jit_us = time_call(lambda f=jitted, x=jax_args: f(*x), args.budget)
        np_us = time_call(lambda f=np_fn, x=np_args: f(*x), args.budget)
        rows.append((name, eq, jit_us, np_us, err))

    vg = vol_value_and_grad()
    jax.block_until_ready(vg(v, kp))
    vol_grad_us = time_call(lambda: vg(v, kp), args.budget)

    outputs = {
        "voxels": v,
        "recon": dev["recon"],
        "heatmaps": dev["heatmaps"],
        "keypoints": kp,
        "affinity": a,
    }
    weights = LossWeights()
    total_vg = jax.jit(jax.value_and_grad(lambda out: losses.skeleton_loss(out, weights)[0]))
    jax.block_until_ready(total_vg(outputs))
    total_us = time_call(lambda: total_vg(outputs), args.budget)

    print(
        f"Paper shapes: G={G}, g={GH}, K={K}, B={B}, T={T}, N={N}; "
        f"backend {jax.default_backend()}, {jax.device_count()} device(s)\n"
    )
    print("| loss | Eq. | jit (us/call) | NumPy (us/call) | NumPy / jit | max rel. diff |")
    print("|---|---|---:|---:|---:|---:|")
    for name, eq, jit_us, np_us, err in rows:
        print(
            f"| {name} | {eq} | {jit_us:,.0f} | {np_us:,.0f} | {np_us / jit_us:.1f} | {err:.1e} |"
        )
    print(f"| volume_fitting fwd+grad | 8 | {vol_grad_us:,.0f} | - | - | - |")
    print(f"| skeleton_loss fwd+grad (all outputs) | 23 | {total_us:,.0f} | - | - | - |")
    print()
    print(memory_report(dev))
    print()
    print(provenance.markdown(stamp))


if __name__ == "__main__":
    main()
