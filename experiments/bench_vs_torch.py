"""main's phase-1 train step against a PyTorch twin of the same layer stack, one process.

    JAX_PLATFORMS=cpu .venv/bin/python experiments/bench_vs_torch.py \
        [--shape cpu paper-channels paper] [--preset cpu|default|tiny] [--set FIELD=VALUE ...] \
        [--steps 5] [--warmup 2] [--threads N] [--only jax|torch] [--out FILE.json]

For every row: first nmjax's real phase-1 train step, timed by `nmjax.bench.bench_skel` exactly as
`nmjax bench` times it (the grain pipeline of synth-arm, the compiled step until its outputs are
ready; "compute" only, the batch loading is not in the step time), then, once the JAX side has
been freed, a PyTorch twin of the same network at the same shapes: forward, the same loss,
`loss.backward()`, gradient clipping by global norm and a `torch.optim.Adam` step on random
occupancy batches (about 5% of the cells filled; the cost does not depend on the values). Both
sides report the median of their per-step times; the ratio is jax / torch (below 1: nmjax faster).

Rows. `--shape` picks named rows (several allowed, default `cpu paper-channels`), the shapes of
issue 14's table:

- `cpu`: the cpu preset, G=32, C=16 (hourglass 16/24/32), K=12, B=2, T=6;
- `paper-channels`: G=32, C=128 with the default preset's hourglass (32/48/72), K=12, B=2, T=10;
- `paper`: the default preset (paper scale), G=64, C=128, K=28, B=1, T=10.

`--set FIELD=VALUE` (nmjax's override syntax, e.g. `--set model.channels=128`) applies on top of
every row's configuration. `--preset P` instead measures one row, `skel_preset("synth-arm", P)`
with the `--set` overrides (it cannot be combined with `--shape`). The data set is synth-arm
(`data/synth-arm` from the working directory unless `--set data.root=...`; generated there on
first use if missing, before anything is timed).

`--threads N` (default: the CPU count) is `torch.set_num_threads(N)` for the twin. JAX runs with
XLA's own default (a thread pool over every core), which is what `nmjax bench` measures; on a
machine where the two differ, say which in the comparison.

The twin (classes below) is written from nmjax's own model code (`nmjax.models.blocks`,
`nmjax.models.detector`, `nmjax.keypoints`, `nmjax.losses`), plainly, the way a PyTorch user
writes it: channels-first `nn.Conv3d` / `nn.ConvTranspose3d` / `nn.GroupNorm`, the coordinate
channels concatenated to every sample (the FeatureNet stem's [occupancy, x, y, z] and the
decoder's [g_t, c_1, g_1, coords] for every frame), `F.interpolate(mode="trilinear",
align_corners=False)` for the decoder's upsampling. It stands for the authors' release, which
issue 14 measured; nmjax's optimisations (the stem's coordinate channels convolved once, the
decoder's frame-independent input share computed once per crop, the sliced CPU convolution) are
deliberately not in it. `tests/test_bench_vs_torch.py` copies nmjax's initial parameters into the
twin (`copy_params`) and checks that both compute the same heatmaps, keypoints, reconstruction,
loss terms and parameter gradients; the script checks at every shape it measures that the two
have the same number of parameters.

Loss: every term of `nmjax.losses.skeleton_loss` with the configuration's weights (Eq. 23):
reconstruction BCE exactly as `losses.reconstruction_bce`; sparsity, separation, volume fitting,
graph local / time / complexity / trajectory as in `losses.py`. Simplifications, none of which
changes the cost measurably (all these terms act on (B, T, K, 4) keypoints, (N, K, K) affinities
or one (B*T, G^3, K) distance matrix, next to 3D convolutions over B*T frames of G^3 cells):

- volume fitting (Eq. 8) computes the nearest keypoint of every cell from the full (B*T, G^3, K)
  matrix of squared distances in one batched call instead of nmjax's per-frame `lax.map` and
  scan, then the exact squared distance to it (so the gradient is the same);
- `weights.vol_target="joints"` (ground-truth joint supervision) is not implemented: the twin
  refuses that configuration.

The network is the released one, as nmjax's is (docs/architecture.md §6): LeakyReLU of slope 0.01,
residual blocks that return branch + skip without an activation and put a GroupNorm after a
projection skip, a residual block before every upsampling of the hourglass, heads ending in a
LeakyReLU and only the fusion in softplus, GroupNorm epsilon 1e-5 (torch's default).

The optimizer is the same as nmjax's phase-1 step: global-norm clipping at `clip_norm` when it
is set (`torch.nn.utils.clip_grad_norm_`), then Adam at `learning_rate` (betas and epsilon are
torch's defaults, the same as optax's). The learning-rate milestones and the epoch restarts
are never reached in a benchmark. The twin keeps torch's default initialisation (the cost does
not depend on the values); the affinity parameters start as nmjax's.

torch is an optional dependency (`pip install -e '.[bench-torch]'`, CPU wheel 2.13.0); without it
the script exits with status 2 unless `--only jax`.
"""

from __future__ import annotations

import argparse
import gc
import math
import os
import platform
import statistics
import sys
import time
from collections.abc import Sequence
from typing import Any

try:
    import torch
    import torch.nn.functional as F
    from torch import nn
except ImportError:  # optional: the twin needs it, `--only jax` does not
    torch = F = nn = None

from nmjax import bench, provenance
from nmjax.config import PRESETS, SkelTrainConfig, skel_preset
from nmjax.config_io import apply_overrides
from nmjax.models.blocks import GN_EPS, LEAK, hourglass_levels, num_groups

DATA = "synth-arm"
INSTALL_HINT = "pip install -e '.[bench-torch]'"
FILL = 0.05  # fraction of occupied cells in the twin's random batches
BCE_EPS = 1e-7  # losses.BCE_EPS
KP_EPS = 1e-6  # keypoints._EPS
COS_EPS = 1e-6  # losses.COS_EPS

# name -> (preset, overrides): the rows of issue 14's table.
SHAPES: dict[str, tuple[str, tuple[str, ...]]] = {
    "cpu": ("cpu", ()),
    "paper-channels": (
        "cpu",
        ("model.channels=128", "model.hourglass_channels=32,48,72", "data.frames=10"),
    ),
    "paper": ("default", ("model.num_keypoints=28", "data.batch_size=1", "data.frames=10")),
}
DEFAULT_SHAPES = ("cpu", "paper-channels")
METRICS = {
    "median_s": "per side, the median of the timed steps' seconds; jax: the compiled phase-1 "
    "step from the placed batch until its outputs are ready (nmjax.bench.bench_skel); torch: "
    "the twin's forward, Eq. 23, backward and optimizer step on random occupancy batches",
    "ratio": "jax median_s / torch median_s (below 1: nmjax faster)",
}

_Module = nn.Module if nn is not None else object


# --- the PyTorch twin (channels-first: (N, C, X, Y, Z)) ----------------------------------------


def coord_channels(n: int, device: Any = None) -> Any:
    """(3, n, n, n): channel d is coordinate d of every cell, linspace(-1, 1, n), 'ij' order."""
    x = torch.linspace(-1.0, 1.0, n, device=device)
    return torch.stack(torch.meshgrid(x, x, x, indexing="ij"), dim=0)


class ConvNormAct(_Module):
    """Conv3d (k, stride s, 'same' padding) -> GroupNorm -> LeakyReLU(0.01)."""

    def __init__(self, in_ch: int, out_ch: int, kernel: int = 3, stride: int = 1):
        super().__init__()
        self.conv = nn.Conv3d(
            in_ch, out_ch, kernel, stride, padding=kernel // 2 if stride == 1 else 0
        )
        self.norm = nn.GroupNorm(num_groups(out_ch), out_ch, eps=GN_EPS)

    def forward(self, x):
        return F.leaky_relu(self.norm(self.conv(x)), LEAK)


class SkipProjection(_Module):
    """1x1x1 conv + GN: the skip of a residual block that changes width."""

    def __init__(self, in_ch: int, out_ch: int):
        super().__init__()
        self.conv = nn.Conv3d(in_ch, out_ch, 1)
        self.norm = nn.GroupNorm(num_groups(out_ch), out_ch, eps=GN_EPS)

    def forward(self, x):
        return self.norm(self.conv(x))


class ResBlock(_Module):
    """conv3 + GN + LReLU, conv3 + GN, plus the input (projected when widths differ); no
    activation after the sum."""

    def __init__(self, in_ch: int, out_ch: int):
        super().__init__()
        self.conv1 = ConvNormAct(in_ch, out_ch, 3)
        self.conv2 = nn.Conv3d(out_ch, out_ch, 3, padding=1)
        self.norm2 = nn.GroupNorm(num_groups(out_ch), out_ch, eps=GN_EPS)
        self.skip = SkipProjection(in_ch, out_ch) if in_ch != out_ch else None

    def forward(self, x):
        y = self.norm2(self.conv2(self.conv1(x)))
        return y + (x if self.skip is None else self.skip(x))


class Pool(_Module):
    """2x2x2 stride-2 convolution + GN + LReLU."""

    def __init__(self, in_ch: int, out_ch: int):
        super().__init__()
        self.block = ConvNormAct(in_ch, out_ch, kernel=2, stride=2)

    def forward(self, x):
        return self.block(x)


class Upsample(_Module):
    """ConvTranspose3d(2, stride 2) + GN + LReLU."""

    def __init__(self, in_ch: int, out_ch: int):
        super().__init__()
        self.conv = nn.ConvTranspose3d(in_ch, out_ch, 2, stride=2)
        self.norm = nn.GroupNorm(num_groups(out_ch), out_ch, eps=GN_EPS)

    def forward(self, x):
        return F.leaky_relu(self.norm(self.conv(x)), LEAK)


class Down(_Module):
    """One hourglass level down: pool, then a residual block changing the width."""

    def __init__(self, in_ch: int, out_ch: int):
        super().__init__()
        self.pool = Pool(in_ch, in_ch)
        self.res = ResBlock(in_ch, out_ch)

    def forward(self, x):
        return self.res(self.pool(x))


class Hourglass(_Module):
    """Pool + residual levels down, a residual skip per level; up: residual block, transposed
    conv, + skip at every level."""

    def __init__(self, channels: int, widths: Sequence[int], size: int):
        super().__init__()
        levels = hourglass_levels(size, len(widths))
        w = (channels, *widths[:levels])
        self.down = nn.ModuleList([Down(w[i], w[i + 1]) for i in range(levels)])
        self.skips = nn.ModuleList([ResBlock(c, c) for c in w[:levels]])
        self.up_res = nn.ModuleList([ResBlock(w[i + 1], w[i + 1]) for i in reversed(range(levels))])
        self.up = nn.ModuleList([Upsample(w[i + 1], w[i]) for i in reversed(range(levels))])

    def forward(self, x):
        skips = []
        for down, skip in zip(self.down, self.skips, strict=True):
            skips.append(skip(x))
            x = down(x)
        for res, up, skip in zip(self.up_res, self.up, reversed(skips), strict=True):
            x = up(res(x)) + skip
        return x


class FeatureNet(_Module):
    """(N, G, G, G) occupancy -> (N, C, g, g, g): CoordConv stem, pool, res, [pool], hourglass,
    res."""

    def __init__(self, channels: int, hourglass_channels: Sequence[int], grid: int, stride: int):
        super().__init__()
        c4, c2 = max(1, channels // 4), max(1, channels // 2)
        self.stem = ConvNormAct(1 + 3, c4, kernel=5)
        self.pool1 = Pool(c4, c4)
        self.res1 = ResBlock(c4, c2)
        self.pool2 = Pool(c2, c2) if stride == 4 else None
        self.hourglass = Hourglass(c2, hourglass_channels, grid // stride)
        self.res2 = ResBlock(c2, channels)

    def forward(self, voxels):
        n, g = voxels.shape[0], voxels.shape[-1]
        coords = coord_channels(g, voxels.device).expand(n, 3, g, g, g)
        x = self.stem(torch.cat([voxels[:, None], coords], dim=1))
        x = self.res1(self.pool1(x))
        if self.pool2 is not None:
            x = self.pool2(x)
        return self.res2(self.hourglass(x))


class VoxelDecoder(_Module):
    """[g_t, c_1, g_1, coords] per frame -> 1x1x1 conv, LReLU, (up x2), C/2 stages, up x2, C/4
    stages, 1x1x1 -> raw logits at G^3."""

    def __init__(self, in_ch: int, channels: int, stride: int):
        super().__init__()
        c2, c4 = max(1, channels // 2), max(1, channels // 4)
        self.upsample_first = stride == 4
        self.inp = nn.Conv3d(in_ch, channels, 1)
        self.up1 = nn.Sequential(ConvNormAct(channels, c2, 3), ConvNormAct(c2, c2, 3))
        self.up2 = nn.Sequential(ConvNormAct(c2, c4, 3), ConvNormAct(c4, c4, 3))
        self.out = nn.Conv3d(c4, 1, 1)

    def forward(self, x):
        x = F.leaky_relu(self.inp(x), LEAK)
        if self.upsample_first:
            x = F.interpolate(x, scale_factor=2, mode="trilinear", align_corners=False)
        x = self.up1(x)
        x = F.interpolate(x, scale_factor=2, mode="trilinear", align_corners=False)
        return self.out(self.up2(x))[:, 0]


def heatmap_to_keypoints(heat):
    """(B, T, K, g, g, g) -> (B, T, K, 4): per-axis expectation of linspace(-1, 1, g), alpha."""
    g = heat.shape[-1]
    mean = heat.mean(dim=(-3, -2, -1))
    alpha = mean / (mean.amax(dim=-1, keepdim=True) + KP_EPS)
    coords = torch.linspace(-1.0, 1.0, g, device=heat.device)
    mus = []
    for others in ((-2, -1), (-3, -1), (-3, -2)):  # marginals on x, y, z
        marginal = heat.sum(dim=others)  # (B, T, K, g)
        prob = marginal / (marginal.sum(dim=-1, keepdim=True) + KP_EPS)
        mus.append((prob * coords).sum(dim=-1))
    return torch.stack([*mus, alpha], dim=-1)


def gaussian_maps(keypoints, sigma: float, n: int):
    """(B, T, K, 4) -> (B, T, K, n, n, n): alpha exp(-|p - mu|^2 / (2 (sigma / n)^2))."""
    grid = coord_channels(n, keypoints.device).permute(1, 2, 3, 0)  # (n, n, n, 3)
    mu = keypoints[..., :3][..., None, None, None, :]  # (B, T, K, 1, 1, 1, 3)
    d2 = ((grid - mu) ** 2).sum(dim=-1)
    alpha = keypoints[..., 3][..., None, None, None]
    return alpha * torch.exp(-d2 / (2 * (sigma / n) ** 2))


def affinity_from_params(params):
    """(N, K, K-1) -> (N, K, K): row softmax scattered off the diagonal (zero diagonal)."""
    n, k = params.shape[0], params.shape[1]
    soft = torch.softmax(params, dim=-1)
    off = ~torch.eye(k, dtype=torch.bool, device=params.device)
    return soft.new_zeros(n, k, k).masked_scatter(off.expand(n, k, k), soft)


class TwinDetector(_Module):
    """nmjax's KeypointDetector, plain PyTorch; the same attribute names (see `copy_params`)."""

    def __init__(self, cfg: Any):  # nmjax.config.DetectorConfig
        super().__init__()
        self.cfg = cfg
        k, c, hg, s = (
            cfg.num_keypoints,
            cfg.channels,
            tuple(cfg.hourglass_channels),
            cfg.heatmap_stride,
        )
        self.features = FeatureNet(c, hg, cfg.grid, s)
        self.st_features = FeatureNet(2 * c, hg, cfg.grid, s)
        self.heat = nn.Conv3d(c, k, 1)
        self.st_heat = nn.Conv3d(2 * c, k, 1)
        self.fuse = nn.Conv3d(2, 1, 1)  # over the two stacked heatmaps, shared by the K maps
        self.decoder = VoxelDecoder(2 * k + c + 3, c, s)
        self.affinity_params = nn.Parameter(torch.ones(cfg.num_affinity, k, k - 1))

    def forward(self, voxels) -> dict[str, Any]:
        """voxels (B, T, G, G, G) -> recon (B, T, G, G, G), heatmaps (B, T, K, g, g, g),
        keypoints (B, T, K, 4), affinity (N, K, K)."""
        b, t, gg = voxels.shape[0], voxels.shape[1], voxels.shape[-1]
        k = self.cfg.num_keypoints
        feats = self.features(voxels.reshape(b * t, gg, gg, gg))  # (B*T, C, g, g, g)
        g = feats.shape[-1]
        heat = F.leaky_relu(self.heat(feats), LEAK).reshape(b, t, k, g, g, g)
        st = F.leaky_relu(self.st_heat(self.st_features(voxels.mean(dim=1))), LEAK)  # (B,K,g^3)
        stacked = torch.stack([heat, st[:, None].expand_as(heat)], dim=3)  # (B, T, K, 2, g^3)
        fused = self.fuse(stacked.reshape(b * t * k, 2, g, g, g))
        heatmaps = F.softplus(fused).reshape(b, t, k, g, g, g)
        keypoints = heatmap_to_keypoints(heatmaps)
        maps = gaussian_maps(keypoints, self.cfg.sigma_g, g)  # (B, T, K, g, g, g)
        first = feats.reshape(b, t, -1, g, g, g)[:, 0]  # c_1
        coords = coord_channels(g, voxels.device)
        dec_in = torch.cat(
            [
                maps,
                first[:, None].expand(b, t, *first.shape[1:]),
                maps[:, :1].expand(b, t, k, g, g, g),
                coords.expand(b, t, 3, g, g, g),
            ],
            dim=2,
        )
        raw = self.decoder(dec_in.reshape(b * t, -1, g, g, g)).reshape(b, t, gg, gg, gg)
        sharp = self.cfg.decoder_sharpness
        recon = torch.sigmoid(sharp * (torch.tanh(raw) + voxels[:, :1] - 0.5))
        return {
            "voxels": voxels,
            "recon": recon,
            "heatmaps": heatmaps,
            "keypoints": keypoints,
            "affinity": affinity_from_params(self.affinity_params),
        }


# --- the loss (nmjax.losses.skeleton_loss, Eq. 23) ---------------------------------------------


def _pairwise_sq_dist(mu):
    return ((mu[..., :, None, :] - mu[..., None, :, :]) ** 2).sum(dim=-1)


def _cosine(u):
    """(..., K, 3) -> (..., K, K) cosine similarity, norms clamped to COS_EPS."""
    unit = u / u.norm(dim=-1, keepdim=True).clamp_min(COS_EPS)
    return unit @ unit.transpose(-1, -2)


def twin_loss(out: dict[str, Any], weights: Any) -> tuple[Any, dict[str, Any]]:
    """(total, terms) of `losses.skeleton_loss` on the twin's outputs (module docstring)."""
    if weights.vol_target != "volume":
        raise ValueError("the torch twin implements weights.vol_target='volume' only")
    voxels, kp, aff = out["voxels"], out["keypoints"], out["affinity"]
    b, t, k = kp.shape[:3]
    mu = kp[..., :3]
    alpha = kp[..., 3]
    iw = weights.intensity_weighted
    # recon: losses.reconstruction_bce
    p = out["recon"].clamp(BCE_EPS, 1.0 - BCE_EPS)
    bce = -(voxels * torch.log(p) + (1.0 - voxels) * torch.log1p(-p))
    recon = bce.mean(dim=(-3, -2, -1)).mean()
    sparse = out["heatmaps"].mean(dim=(-3, -2, -1)).abs().mean()
    # separation: trajectories centred over time, squared distance averaged over time
    s = mu - mu.mean(dim=1, keepdim=True)
    e = torch.exp(-_pairwise_sq_dist(s).mean(dim=1) / (2 * weights.sep_sigma**2))  # (B, K, K)
    off = 1.0 - torch.eye(k, device=kp.device)
    sep = ((e * off).sum(dim=(-2, -1)) / max(k * (k - 1), 1)).mean()
    # volume fitting: nearest keypoint of every occupied cell
    g = voxels.shape[-1]
    points = coord_channels(g, kp.device).reshape(3, -1).T  # (G^3, 3)
    occ = voxels.reshape(b * t, -1)
    m = mu.reshape(b * t, k, 3)
    with torch.no_grad():
        sq = (m**2).sum(-1)[:, None, :] - 2.0 * points @ m.transpose(1, 2)  # (B*T, G^3, K)
        nearest = sq.argmin(dim=-1)  # (B*T, G^3)
    closest = torch.gather(m, 1, nearest[..., None].expand(-1, -1, 3))  # (B*T, G^3, 3)
    dist = ((points - closest) ** 2).sum(dim=-1)
    vol = ((occ * dist).sum(-1) / occ.sum(-1).clamp_min(1.0)).mean()
    # graph terms
    a = aff.amax(dim=0)  # at ties (the initial affinities) the gradient splits, as jnp.max
    dist_kk = _pairwise_sq_dist(mu)  # (B, T, K, K)
    local_terms = a * dist_kk
    time_terms = a * (dist_kk - dist_kk.mean(dim=1, keepdim=True)).abs()
    if iw:
        local_terms = local_terms * alpha[..., None]
        time_terms = time_terms * alpha[..., None]
    sq_aff = aff**2
    complexity = (sq_aff.sum(0) ** 2 - (sq_aff**2).sum(0)).mean()
    vel = mu[:, 1:] - mu[:, :-1]
    acc = vel[:, 1:] - vel[:, :-1]
    c_vel = (1.0 - _cosine(vel)) / 2.0
    c_acc = (1.0 - _cosine(acc)) / 2.0
    if iw:
        w_vel = (alpha[:, 1:] + alpha[:, :-1]) / 2
        w_acc = (w_vel[:, 1:] + w_vel[:, :-1]) / 2
        c_vel, c_acc = c_vel * w_vel[..., None], c_acc * w_acc[..., None]
    cost = c_vel.reshape(-1, k, k).mean(0) + c_acc.reshape(-1, k, k).mean(0)
    terms = {
        "recon": recon,
        "sparse": sparse,
        "sep": sep,
        "vol": vol,
        "local": local_terms.mean(),
        "time": time_terms.mean(),
        "complex": complexity,
        "traj": (a * cost).mean(),
    }
    total = sum(getattr(weights, name) * value for name, value in terms.items())
    return total, terms


# --- nmjax's parameters into the twin (the tests' equality check) ------------------------------


def in_twin_layout(state: Any, twin: Any) -> dict[str, Any]:
    """nmjax parameters (or gradients) `state`, an nnx.State of nnx.Param, as the twin's tensors.

    Paths map one to one (the twin uses nmjax's attribute names; nnx.Sequential's `layers` level
    is dropped): a Conv3D kernel (k, k, k, in, out) becomes Conv3d's (out, in, k, k, k), and the
    transposed convolution's ConvTranspose3d (in, out, k, k, k); GroupNorm scale -> weight; the
    fuse Linear's (2, 1) kernel -> Conv3d (1, 2, 1, 1, 1). Raises ValueError when a parameter of
    either side has no counterpart or a different shape.

    Returns:
      {twin parameter name: float32 numpy array in the twin's layout}.
    """
    import numpy as np
    from flax import nnx

    targets = dict(twin.named_parameters())
    modules = dict(twin.named_modules())
    out = {}
    for path, value in nnx.to_flat_state(state):
        names = [str(p) for p in path if p != "layers"]
        leaf, owner = names[-1], ".".join(names[:-1])
        leaf = {"kernel": "weight", "scale": "weight"}.get(leaf, leaf)
        name = f"{owner}.{leaf}" if owner else leaf
        if name not in targets:
            raise ValueError(f"nmjax parameter {'/'.join(names)} has no twin {name}")
        arr = np.array(value[...], dtype=np.float32)
        if names[-1] == "kernel" and owner == "fuse":
            arr = arr.T.reshape(1, 2, 1, 1, 1)
        elif names[-1] == "kernel" and isinstance(modules[owner], nn.ConvTranspose3d):
            arr = arr.transpose(3, 4, 0, 1, 2)
        elif names[-1] == "kernel":
            arr = arr.transpose(4, 3, 0, 1, 2)
        if tuple(arr.shape) != tuple(targets[name].shape):
            raise ValueError(f"{name}: twin {tuple(targets[name].shape)}, nmjax {arr.shape}")
        out[name] = np.ascontiguousarray(arr)
    missing = set(targets) - set(out)
    if missing:
        raise ValueError(f"twin parameters without an nmjax counterpart: {sorted(missing)}")
    return out


def copy_params(detector: Any, twin: Any) -> int:
    """Copies every nnx.Param of nmjax's `detector` into `twin` (`in_twin_layout`); returns how
    many tensors were copied."""
    from flax import nnx

    targets = dict(twin.named_parameters())
    arrays = in_twin_layout(nnx.state(detector, nnx.Param), twin)
    with torch.no_grad():
        for name, arr in arrays.items():
            targets[name].copy_(torch.from_numpy(arr))
    return len(arrays)


def twin_param_count(twin: Any) -> int:
    return sum(p.numel() for p in twin.parameters())


def nmjax_param_count(model_cfg: Any) -> int:
    """Size of every nnx.Param of nmjax's KeypointDetector at `model_cfg`."""
    import jax
    from flax import nnx

    from nmjax.models.detector import KeypointDetector

    model = KeypointDetector(model_cfg, rngs=nnx.Rngs(0))
    return sum(int(x.size) for x in jax.tree.leaves(nnx.state(model, nnx.Param)))


# --- timing ------------------------------------------------------------------------------------


def random_voxels(shape: Sequence[int], generator: Any) -> Any:
    """(B, T, G, G, G) float32 occupancy in {0, 1}, about FILL of the cells set."""
    return (torch.rand(*shape, generator=generator) < FILL).float()


def bench_torch(cfg: SkelTrainConfig, steps: int, warmup: int, seed: int = 0) -> dict[str, Any]:
    """Per-step times of the twin's train step (forward, loss, backward, clip, Adam) at `cfg`."""
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    m = cfg.model
    shape = (cfg.data.batch_size, cfg.data.frames, m.grid, m.grid, m.grid)
    twin = TwinDetector(m)
    opt = torch.optim.Adam(twin.parameters(), lr=cfg.learning_rate)
    params = list(twin.parameters())
    times, losses = [], []
    for i in range(warmup + steps):
        voxels = random_voxels(shape, gen)
        tic = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        loss, _ = twin_loss(twin(voxels), cfg.weights)
        loss.backward()
        if cfg.clip_norm and cfg.clip_norm > 0:
            torch.nn.utils.clip_grad_norm_(params, cfg.clip_norm)
        opt.step()
        elapsed = time.perf_counter() - tic
        losses.append(float(loss.detach()))
        if i >= warmup:
            times.append(elapsed)
    if not all(math.isfinite(v) for v in losses):
        raise RuntimeError(f"bench_vs_torch: the twin's loss became {losses}")
    return {
        "step_s": times,
        "median_s": statistics.median(times),
        "mean_s": statistics.fmean(times),
        "params": twin_param_count(twin),
        "threads": torch.get_num_threads(),
        "last_loss": losses[-1],
    }


def bench_jax(cfg: SkelTrainConfig, preset: str, steps: int, warmup: int) -> dict[str, Any]:
    """`nmjax.bench.bench_skel`'s row (it times each step from the placed batch to the outputs
    being ready) and the median and mean of its per-step compute times."""
    row = bench.bench_skel(cfg, preset, steps, warmup)
    return {
        "row": row,
        "step_s": row["compute_s_steps"],
        "median_s": row["compute_s_median"],
        "mean_s": row["compute_s_per_step"],
    }


def free_jax() -> None:
    """Drops JAX's compiled executables and the arrays nobody holds any more."""
    import jax

    gc.collect()
    jax.clear_caches()
    gc.collect()


# --- command line ------------------------------------------------------------------------------


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="bench_vs_torch.py",
        description="nmjax's phase-1 train step against a PyTorch twin, same shapes, one process.",
    )
    parser.add_argument(
        "--shape",
        nargs="+",
        action="extend",
        choices=sorted(SHAPES),
        default=None,
        help=f"named rows (default: {' '.join(DEFAULT_SHAPES)})",
    )
    parser.add_argument(
        "--preset",
        choices=PRESETS,
        default=None,
        help="one row of this preset (with --set) instead of --shape",
    )
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="config override applied to every row (e.g. model.channels=128)",
    )
    parser.add_argument("--steps", type=int, default=5, help="timed steps per side")
    parser.add_argument("--warmup", type=int, default=2, help="untimed steps first")
    parser.add_argument(
        "--threads", type=int, default=None, help="torch.set_num_threads (default: CPU count)"
    )
    parser.add_argument("--only", choices=("jax", "torch"), default=None, help="one side only")
    parser.add_argument("--out", default=None, help="write the environment and rows as JSON")
    args = parser.parse_args(list(argv))
    if args.steps < 1 or args.warmup < 0:
        parser.error(f"--steps must be >= 1 and --warmup >= 0, got {args.steps}, {args.warmup}")
    if args.preset is not None and args.shape is not None:
        parser.error("--preset measures one row of its own; give it or --shape, not both")
    if args.threads is None:
        args.threads = os.cpu_count() or 1
    if args.threads < 1:
        parser.error(f"--threads must be >= 1, got {args.threads}")
    return args


def rows_of(args: argparse.Namespace) -> list[tuple[str, str, SkelTrainConfig]]:
    """(name, preset, config) of every row, in order."""
    if args.preset is not None:
        cfg = apply_overrides(skel_preset(DATA, args.preset), args.overrides)
        return [(f"preset:{args.preset}", args.preset, cfg)]
    out = []
    for name in args.shape or DEFAULT_SHAPES:
        preset, shape_overrides = SHAPES[name]
        cfg = apply_overrides(skel_preset(DATA, preset), [*shape_overrides, *args.overrides])
        out.append((name, preset, cfg))
    return out


def _version(module: str) -> str | None:
    from importlib import metadata

    try:
        return metadata.version(module)
    except metadata.PackageNotFoundError:
        return None


def environment(args: argparse.Namespace) -> dict[str, Any]:
    """CPU count, load average at the start, versions and the thread settings (the commit is in
    the results file's provenance stamp)."""
    env = {
        "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "cpu_count": os.cpu_count(),
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "load_avg_5min": round(os.getloadavg()[1], 2),
        "machine": platform.machine(),
        "python": platform.python_version(),
        "torch_threads": args.threads,
        "JAX_PLATFORMS": os.environ.get("JAX_PLATFORMS"),
        "XLA_FLAGS": os.environ.get("XLA_FLAGS"),
    }
    for name in ("jax", "jaxlib", "flax", "numpy", "torch"):
        env[name] = _version(name)
    return env


def shape_of(cfg: SkelTrainConfig) -> dict[str, Any]:
    m = cfg.model
    return {
        "G": m.grid,
        "C": m.channels,
        "hourglass": list(m.hourglass_channels),
        "K": m.num_keypoints,
        "B": cfg.data.batch_size,
        "T": cfg.data.frames,
        "stride": m.heatmap_stride,
        "compute_dtype": m.compute_dtype,
    }


def format_table(rows: list[dict[str, Any]]) -> str:
    header = (
        f"{'shape':<16} {'G':>3} {'C':>4} {'K':>3} {'B':>2} {'T':>3} "
        f"{'jax s (median)':>15} {'torch s (median)':>17} {'jax/torch':>10}"
    )
    lines = [header, "-" * len(header)]

    def cell(side: dict | None, width: int) -> str:
        return f"{side['median_s']:>{width}.3f}" if side else f"{'-':>{width}}"

    for r in rows:
        s = r["shape"]
        ratio = f"{r['ratio']:>10.2f}" if r["ratio"] is not None else f"{'-':>10}"
        lines.append(
            f"{r['name']:<16} {s['G']:>3} {s['C']:>4} {s['K']:>3} {s['B']:>2} {s['T']:>3} "
            f"{cell(r['jax'], 15)} {cell(r['torch'], 17)} {ratio}"
        )
    return "\n".join(lines)


def main(argv: Sequence[str]) -> int:
    try:
        args = parse_args(argv)
        todo = rows_of(args)
    except ValueError as err:
        print(f"bench_vs_torch: {err}", file=sys.stderr)
        return 2
    if args.only != "jax" and torch is None:
        print(f"bench_vs_torch: PyTorch is not installed; {INSTALL_HINT}", file=sys.stderr)
        return 2
    if torch is not None:
        torch.set_num_threads(args.threads)
    stamp = provenance.stamp(METRICS)
    env = environment(args)
    print(f"commit={provenance.describe_commit(stamp)}")
    print(" ".join(f"{k}={v}" for k, v in env.items()))
    rows = []
    for name, preset, cfg in todo:
        row: dict[str, Any] = {"name": name, "preset": preset, "shape": shape_of(cfg)}
        row["overrides"] = [*SHAPES.get(name, (None, ()))[1], *args.overrides]
        row["jax"] = row["torch"] = None
        if args.only != "torch":
            try:
                row["jax"] = bench_jax(cfg, preset, args.steps, args.warmup)
            except (ValueError, FileNotFoundError) as err:
                print(f"bench_vs_torch: {name}: {err}", file=sys.stderr)
                return 2
            free_jax()
            print(f"{name}: jax {row['jax']['median_s']:.3f} s/step (median)", flush=True)
        if args.only != "jax":
            row["torch"] = bench_torch(cfg, args.steps, args.warmup, seed=cfg.seed)
            row["torch"]["nmjax_params"] = nmjax_param_count(cfg.model)
            free_jax()
            print(f"{name}: torch {row['torch']['median_s']:.3f} s/step (median)", flush=True)
            if row["torch"]["params"] != row["torch"]["nmjax_params"]:
                print(
                    f"bench_vs_torch: {name}: the twin has {row['torch']['params']} parameters, "
                    f"nmjax {row['torch']['nmjax_params']}: the layer stacks differ",
                    file=sys.stderr,
                )
        both = row["jax"] is not None and row["torch"] is not None
        row["ratio"] = row["jax"]["median_s"] / row["torch"]["median_s"] if both else None
        rows.append(row)
    bench.print_and_save(format_table(rows), args.out, env, args, rows, stamp)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
