"""Matplotlib pictures of phase-1 results (Agg backend, written atomically)."""

from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from nmjax import atomic  # noqa: E402


def save_figure(
    fig, path: str | os.PathLike, *, title: str | None = None, dpi: int = 100, tight: bool = True
) -> None:
    """Writes a matplotlib figure as PNG to `path` atomically, then closes it.

    Args:
      fig: the figure.
      path: the .png file (its folder is created).
      title: optional figure title (suptitle), set before the layout.
      dpi: resolution.
      tight: apply `fig.tight_layout()` first.
    """
    if title is not None:
        fig.suptitle(title)
    if tight:
        fig.tight_layout()
    with atomic.writer(path, "wb") as f:
        fig.savefig(f, format="png", dpi=dpi)
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
