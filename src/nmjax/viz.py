"""Every picture nmjax draws: matplotlib (Agg backend) figures and GIFs, written atomically.

Phase 1: the keypoints over the voxels of a frame (`plot_keypoints`, the training run's
validation figures) and the extracted tree (`draw_skeleton`, `extract-skeleton`). Phase 2 and the
tasks: observed against generated skeletons (`plot_motion`, validation of `train-dyn`) and 3D
frames of several motions as a GIF and a PNG strip (`write_motion_pictures`, `generate`,
`interpolate`, `retarget`). Evaluation: the generation measures against the horizon
(`plot_generation`) and M-CD against the sampling rate (`plot_mcd`). `nmjax rig`: the skinned
surface over the capture's points (`draw_rig`). Callers import this module
where they draw, so that commands which draw nothing do not load matplotlib.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from nmjax import atomic  # noqa: E402
from nmjax.metrics import voxel_points  # noqa: E402

if TYPE_CHECKING:
    from nmjax.skeleton import Skeleton

# One colour per motion panel of `render_frames`, cycled.
COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")


def save_figure(
    fig,
    path: str | os.PathLike,
    *,
    title: str | None = None,
    dpi: int = 100,
    tight: bool = True,
    crop: bool = False,
) -> None:
    """Writes a matplotlib figure as PNG to `path` atomically, then closes it.

    Args:
      fig: the figure.
      path: the .png file (its folder is created).
      title: optional figure title (suptitle), set before the layout.
      dpi: resolution.
      tight: apply `fig.tight_layout()` first.
      crop: cut the saved image to the drawn content (`bbox_inches="tight"`).
    """
    if title is not None:
        fig.suptitle(title)
    if tight:
        fig.tight_layout()
    with atomic.writer(path, "wb") as f:
        fig.savefig(f, format="png", dpi=dpi, bbox_inches="tight" if crop else None)
    plt.close(fig)


def strongest_edges(affinity: np.ndarray) -> list[tuple[int, int, float]]:
    """For each keypoint k its most affine other keypoint under max_n A_n: (k, k', a_kk')."""
    from nmjax.skeleton import influence as max_over_n

    influence = max_over_n(affinity)
    np.fill_diagonal(influence, -np.inf)  # never its own partner
    partners = influence.argmax(axis=1)
    return [(k, int(j), float(influence[k, j])) for k, j in enumerate(partners)]


def plot_keypoints(
    path: str | os.PathLike,
    voxels: np.ndarray,
    keypoints: np.ndarray,
    affinity: np.ndarray,
    title: str = "",
    max_points: int = 4000,
    seed: int = 0,
) -> None:
    """Saves a 3D scatter of the occupied voxels, the keypoints and their strongest affinity edges.

    Args:
      path: PNG file to write.
      voxels: (G, G, G) occupancy of one frame.
      keypoints: (K, 4) keypoints of that frame (xyz in [-1, 1], alpha).
      affinity: (N, K, K) or (K, K) affinity; each keypoint is joined to its argmax partner.
      title: figure title.
      max_points: occupied voxels drawn at most (random subset).
      seed: subset seed.
    """
    voxels = np.asarray(voxels)
    keypoints = np.asarray(keypoints)
    g = voxels.shape[0]
    axis = np.linspace(-1.0, 1.0, g)
    idx = np.argwhere(voxels > 0.5)
    if len(idx) > max_points:
        idx = idx[np.random.default_rng(seed).choice(len(idx), max_points, replace=False)]
    pts = axis[idx] if len(idx) else np.zeros((0, 3))
    fig = plt.figure(figsize=(6, 6))
    ax = fig.add_subplot(projection="3d")
    ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=1, c="0.6", alpha=0.25, depthshade=False)
    mu, alpha = keypoints[:, :3], np.clip(keypoints[:, 3], 0.0, 1.0)
    for k, j, _ in strongest_edges(affinity):
        ax.plot(*zip(mu[k], mu[j], strict=True), c="tab:blue", lw=1.0 + alpha[k], alpha=0.8)
    colors = plt.get_cmap("tab20")(np.arange(len(mu)) % 20)
    colors[:, 3] = 0.3 + 0.7 * alpha
    ax.scatter(mu[:, 0], mu[:, 1], mu[:, 2], s=20 + 60 * alpha, c=colors, depthshade=False)
    for k in range(len(mu)):
        ax.text(*mu[k], str(k), fontsize=7)
    ax.set_xlim(-1, 1)
    ax.set_ylim(-1, 1)
    ax.set_zlim(-1, 1)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    ax.set_title(title)
    save_figure(fig, path, tight=False)


def draw_skeleton(
    path: str | os.PathLike,
    skeleton: Skeleton,
    keypoints: np.ndarray,
    voxels: np.ndarray,
    keep: np.ndarray,
    title: str = "",
) -> None:
    """Saves a 3D picture of the tree on `keypoints` over the occupied cells of `voxels`.

    Args:
      path: PNG file to write.
      skeleton: the tree (its edges and root are drawn).
      keypoints: (K, 4) keypoints of the example frame (xyz in [-1, 1], alpha).
      voxels: (G, G, G) occupancy of that frame.
      keep: (K,) bool, the keypoints kept after pruning; the others and their edges are faded.
      title: axes title.
    """
    cells = voxel_points(voxels)
    mu = keypoints[:, :3]
    fig = plt.figure(figsize=(6, 6))
    ax = fig.add_subplot(projection="3d")
    if len(cells):
        ax.scatter(*cells.T, s=2, c="0.55", alpha=0.15, depthshade=False)
    for parent, child in skeleton.edges():
        faded = not (keep[parent] and keep[child])
        ax.plot(*mu[[parent, child]].T, c="tab:blue", lw=2, alpha=0.15 if faded else 0.9)
    colours = np.where(keep, "tab:red", "0.5")
    ax.scatter(*mu[keep].T, c=colours[keep], s=25, depthshade=False)
    ax.scatter(*mu[~keep].T, c=colours[~keep], s=15, alpha=0.25, depthshade=False)
    ax.scatter(*mu[skeleton.root], c="k", s=60, marker="*", depthshade=False)
    for k in range(len(mu)):
        ax.text(*mu[k], str(k), fontsize=6, alpha=0.9 if keep[k] else 0.3)
    ax.set(xlim=(-1, 1), ylim=(-1, 1), zlim=(-1, 1), xlabel="x", ylabel="y", zlabel="z")
    ax.set_title(title, fontsize=9)
    save_figure(fig, path, dpi=120, tight=False, crop=True)


def draw_pruned_tree(
    ax,
    keypoints: np.ndarray,
    parents,
    keep: np.ndarray,
    points: np.ndarray | None = None,
    title: str = "",
) -> None:
    """A pruned tree on one frame's keypoints over the body's points, on 3D axes `ax` (one cell
    of a results figure).

    Args:
      keypoints: (K, >= 3) the frame's keypoints in the cube [-1, 1]^3.
      parents: (K,) the pruned tree, a root its own parent.
      keep: (K,) bool, the kept nodes: only they and the bones between them are drawn.
      points: (N, 3) the frame's occupied cells, drawn faintly behind; None: none.
      title: the cell's title.
    """
    kp = np.asarray(keypoints)[:, :3]
    keep = np.asarray(keep, bool)
    if points is not None and len(points):
        ax.scatter(
            *np.asarray(points).reshape(-1, 3).T, s=0.6, c="0.6", alpha=0.25, depthshade=False
        )
    for k, p in enumerate(parents):
        if p != k and keep[k]:
            ax.plot(*kp[[p, k]].T, "-", c="tab:blue", lw=1.8)
    ax.scatter(*kp[keep].T, s=10, c="tab:red", depthshade=False)
    ax.set(xlim=(-1, 1), ylim=(-1, 1), zlim=(-1, 1), xticks=[], yticks=[], zticks=[])
    ax.set_title(title, fontsize=7)


def plot_motion(
    path: str | os.PathLike,
    observed: np.ndarray,
    generated: np.ndarray,
    parents: tuple[int, ...],
    t_cond: int,
    columns: int = 6,
) -> None:
    """Observed (top) and generated (bottom) skeletons, x-y projection, at `columns` frames.

    Args:
      path: PNG file, written atomically.
      observed, generated: (T, K, 4) keypoints.
      parents: (K,) the skeleton.
      t_cond: frames given to the model; the frames after it are generated.
      columns: frames shown, spread evenly over the sequence.
    """
    frames = np.unique(np.linspace(0, len(observed) - 1, columns).astype(int))
    fig, axes = plt.subplots(2, len(frames), figsize=(2.2 * len(frames), 4.6), squeeze=False)
    both = np.concatenate([observed[..., :2], generated[..., :2]]).reshape(-1, 2)
    lo, hi = both.min(0) - 0.1, both.max(0) + 0.1
    for row, (label, x) in enumerate((("observed", observed), ("generated", generated))):
        for col, t in enumerate(frames):
            ax = axes[row, col]
            for k, p in enumerate(parents):
                if p != k:
                    ax.plot(x[t, [p, k], 0], x[t, [p, k], 1], "-", color="tab:blue", lw=1.5)
            alpha = np.clip(x[t, :, 3], 0, 1)  # intensity: dark = 0, yellow = 1
            ax.scatter(x[t, :, 0], x[t, :, 1], s=8, c=alpha, cmap="viridis", vmin=0, vmax=1)
            ax.set_xlim(lo[0], hi[0])
            ax.set_ylim(lo[1], hi[1])
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            kind = "cond" if t < t_cond else "gen"
            ax.set_title(f"{label} t={t}" + (f" ({kind})" if row else ""), fontsize=8)
    save_figure(fig, path, dpi=80)


# --- motions as GIF and PNG strip ----------------------------------------------------------------


def _skeleton_axes(fig, rows: int, cols: int, index: int, lo, hi, title: str):
    ax = fig.add_subplot(rows, cols, index, projection="3d")
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(np.maximum(hi - lo, 1e-3))
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_zticks([])
    ax.set_title(title, fontsize=8)
    ax.view_init(elev=15, azim=-60)
    return ax


def _draw_pose(ax, pose: np.ndarray, parents, color: str, points: np.ndarray | None = None):
    if points is not None and len(points):
        ax.scatter(*points.T, s=0.5, c="0.65", alpha=0.3, depthshade=False)
    for k, p in enumerate(parents):
        if p != k:
            ax.plot(*zip(pose[p, :3], pose[k, :3], strict=True), "-", color=color, lw=1.5)
    ax.scatter(*pose[:, :3].T, s=6, c=color, depthshade=False)


def render_frames(
    motions: list[np.ndarray],
    labels: list[str],
    parents,
    clouds: list[np.ndarray | None] | None = None,
    size: float = 2.6,
) -> list[np.ndarray]:
    """One RGB image per frame with a 3D panel per motion.

    Args:
      motions: list of (T, K, >=3) joint positions (equal T).
      labels: panel titles.
      parents: (K,) the skeleton.
      clouds: optional per panel a (T, P, 3) point cloud drawn behind the skeleton.
      size: inches per panel.

    Returns:
      list of T (H, W, 3) uint8 images.
    """
    extra = [c.reshape(-1, 3) for c in (clouds or []) if c is not None]
    stacked = np.concatenate([m[..., :3].reshape(-1, 3) for m in motions] + extra)
    lo, hi = stacked.min(0) - 0.05, stacked.max(0) + 0.05
    images = []
    for t in range(motions[0].shape[0]):
        fig = plt.figure(figsize=(size * len(motions), size))
        for i, (motion, label) in enumerate(zip(motions, labels, strict=True)):
            ax = _skeleton_axes(fig, 1, len(motions), i + 1, lo, hi, f"{label} t={t}")
            cloud = None if clouds is None or clouds[i] is None else clouds[i][t]
            _draw_pose(ax, motion[t], parents, COLORS[i % len(COLORS)], cloud)
        fig.tight_layout()
        fig.canvas.draw()
        images.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
        plt.close(fig)
    return images


def write_gif(path: str | os.PathLike, images: list[np.ndarray], fps: float = 8.0) -> None:
    """Animated GIF of equally sized RGB frames, written atomically."""
    import imageio.v3 as iio

    data = iio.imwrite("<bytes>", np.stack(images), extension=".gif", duration=1000 / fps, loop=0)
    with atomic.writer(path, "wb") as f:
        f.write(data)


def write_strip(path: str | os.PathLike, images: list[np.ndarray], columns: int = 6) -> None:
    """PNG of `columns` frames spread over the sequence, stacked vertically, atomically."""
    import imageio.v3 as iio

    idx = np.unique(np.linspace(0, len(images) - 1, columns).astype(int))
    buffer = io.BytesIO()
    iio.imwrite(buffer, np.concatenate([images[i] for i in idx], axis=0), extension=".png")
    with atomic.writer(path, "wb") as f:
        f.write(buffer.getvalue())


def write_motion_pictures(
    stem: os.PathLike,
    motions: list[np.ndarray],
    labels: list[str],
    parents,
    clouds: list[np.ndarray | None] | None = None,
) -> None:
    """`stem`.gif (the whole motion) and `stem`.png (a strip of frames) of `render_frames`."""
    stem = Path(stem)
    images = render_frames(motions, labels, parents, clouds=clouds)
    write_gif(stem.with_name(stem.name + ".gif"), images)
    write_strip(stem.with_name(stem.name + ".png"), images)


# --- a rig over its capture (`nmjax rig`) --------------------------------------------------------


def draw_rig(
    path: str | os.PathLike,
    frames: np.ndarray,
    captured: np.ndarray,
    surface: np.ndarray,
    joints: np.ndarray,
    parents,
    title: str = "",
) -> None:
    """A rig's skinned surface over its capture's points at a few frames, one 3D panel a frame
    (RIG.png of `nmjax rig`: what to look at before opening the .glb).

    Coordinates are in glTF's axes (+Y up, +Z towards the viewer, as the file holds them); the
    panels show +Y upwards, seen from the front, all at the same scale.

    Args:
      path: PNG file, written atomically.
      frames: (F,) the frame numbers shown (panel titles).
      captured: (F, N, 3) the capture's points at those frames (grey).
      surface: (F, V, 3) the skinned mesh vertices or points at those frames (coloured).
      joints: (F, J, 3) the rig's joints; parents: (J,) its tree, the root its own parent.
      title: the figure's title.
    """

    def shown(x: np.ndarray) -> np.ndarray:  # glTF (x, y up, z front) -> matplotlib (x, -z, y)
        x = np.asarray(x, np.float64)
        return np.stack([x[..., 0], -x[..., 2], x[..., 1]], axis=-1)

    captured, surface, joints = shown(captured), shown(surface), shown(joints)
    every = np.concatenate([captured.reshape(-1, 3), surface.reshape(-1, 3)])
    lo, hi = every.min(axis=0), every.max(axis=0)
    pad = 0.05 * float(np.max(hi - lo))
    lo, hi = lo - pad, hi + pad
    fig = plt.figure(figsize=(3.2 * len(frames), 3.6))
    for i, t in enumerate(frames):
        ax = _skeleton_axes(fig, 1, len(frames), i + 1, lo, hi, f"frame {int(t)}")
        ax.view_init(elev=12, azim=-80)
        ax.scatter(*captured[i].T, s=0.4, c="0.55", alpha=0.35, depthshade=False)
        ax.scatter(*surface[i].T, s=0.6, c="tab:orange", alpha=0.5, depthshade=False)
        for k, p in enumerate(parents):
            if p != k:
                ax.plot(*joints[i, [p, k]].T, "-", color="tab:blue", lw=1.8)
        ax.scatter(*joints[i].T, s=10, c="tab:blue", depthshade=False)
    save_figure(fig, path, title=title or None, dpi=110)


# --- evaluation plots ----------------------------------------------------------------------------


def plot_generation(path: str | os.PathLike, gen: dict, *, reference: str, title: str = "") -> None:
    """Each generation measure against the horizon, one line per method, 95% CI error bars.

    Args:
      path: PNG file to write.
      gen: the generation results (`nmjax.evaluate.evaluate_generation`): "methods" maps a
        method to {horizon: {measure: {"mean", "ci95"}}}, "real" holds the test clips' own values.
      reference: the label of the test clips' line (dashed), drawn where they have the measure.
      title: figure title.
    """
    measures = ("diversity", "set_diversity", "bone_error", "set_distance")
    labels = ("diversity (APD per clip)", "set diversity", "bone-length error", "set distance")
    horizons = [int(h) for h in next(iter(gen["methods"].values()))]
    fig, axes = plt.subplots(1, 4, figsize=(14, 3.4))
    for ax, measure, label in zip(axes, measures, labels, strict=True):
        series = dict(gen["methods"])
        if measure in ("set_diversity", "bone_error"):
            series[reference] = gen["real"]
        for method, by_n in series.items():
            n = [int(h) for h in by_n if measure in by_n[h]]
            means = np.array([by_n[str(h)][measure]["mean"] for h in n], np.float64)
            ci = np.nan_to_num(np.array([by_n[str(h)][measure]["ci95"] for h in n], np.float64))
            style = "--" if method == reference else "-"
            ax.errorbar(n, means, yerr=ci, fmt=style, marker="o", ms=3, capsize=3, label=method)
        ax.set_xscale("log")
        ax.set_xticks(horizons, [str(h) for h in horizons])
        ax.minorticks_off()
        ax.set_xlim(min(horizons) / 1.4, max(horizons) * 1.4)
        ax.set_xlabel("horizon N (generated frames)")
        ax.set_title(label, fontsize=9)
    axes[1].legend(fontsize=7)  # the panel with every method and the reference
    save_figure(fig, path, title=title or None)


def plot_mcd(path: str | os.PathLike, mcd: dict, title: str = "") -> None:
    """M-CD against SR with 95% CI error bars, one line per method (Fig. 5 style).

    Args:
      path: PNG file to write.
      mcd: {method: {SR: {"mean", "ci95"}}} with the rates as strings (the JSON's form).
      title: axes title.
    """
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    for method, by_rate in mcd.items():
        rates = [int(r) for r in by_rate]
        means = np.array([by_rate[str(r)]["mean"] for r in rates])
        ci = np.nan_to_num(np.array([by_rate[str(r)]["ci95"] for r in rates]))
        ax.errorbar(rates, means, yerr=ci, marker="o", ms=3, capsize=3, label=method)
    ax.set_xlabel("sampling rate SR (frames between keyframes)")
    ax.set_ylabel("M-CD x1e3")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    save_figure(fig, path)


def plot_phase2_curves(
    path: str | os.PathLike, curves: dict[str, list[dict[str, float]]], title: str = ""
) -> None:
    """Phase 2's learning curves, one colour per model, log scale.

    Three panels: the training reconstruction (Eq. 3, best of S posterior samples; dashed grey:
    predicting each frame by the one before), the validation reconstruction (solid: one sample,
    dotted: best of S; dashed grey: repeating the last pose) and the validation generation after
    T/4 observed frames (dashed grey: holding the last observed pose).

    Args:
      path: PNG file to write.
      curves: {model: the run's metric records (metrics.jsonl: dicts with "step" and the logged
        "train/..." or "val/..." values)}.
      title: figure title.
    """
    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    for (model, records), color in zip(curves.items(), COLORS, strict=False):
        train = [r for r in records if "train/recon" in r]
        val = [r for r in records if "val/recon" in r]
        axes[0].plot([r["step"] for r in train], [r["train/recon"] for r in train], color=color)
        if train and "train/last_pose" in train[0]:
            last = [r["train/last_pose"] for r in train]
            axes[0].plot([r["step"] for r in train], last, color="gray", ls="--", lw=0.8)
        steps = [r["step"] for r in val]
        axes[1].plot(steps, [r["val/recon"] for r in val], color=color, label=model)
        best = [r["val/recon_best"] for r in val]
        axes[1].plot(steps, best, color=color, ls=":", label=f"{model}, best of S")
        axes[2].plot(steps, [r["val/gen"] for r in val], color=color, label=model)
        if val:
            axes[1].axhline(val[-1]["val/last_pose"], color="gray", ls="--")
            axes[2].axhline(val[-1]["val/gen_hold"], color="gray", ls="--")
    axes[0].set_title("train: Eq. 3 reconstruction, best of S (dashed: last pose)", fontsize=10)
    axes[1].set_title("val: posterior reconstruction (dashed: last pose)", fontsize=10)
    axes[2].set_title("val: generation after T/4 frames (dashed: hold)", fontsize=10)
    for ax in axes:
        ax.set_yscale("log")
        ax.set_xlabel("step")
    axes[1].legend(fontsize=8)
    save_figure(fig, path, title=title, dpi=90)
