"""The pictures of the task commands (`nmjax.tasks.run_generate`, `run_interpolate`,
`run_retarget`): per motion a GIF and a PNG strip of 3D skeleton frames (matplotlib Agg, imageio),
written atomically.
"""

from __future__ import annotations

import io as _io
from pathlib import Path

import numpy as np

from nmjax import atomic

COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")


# --- pictures -------------------------------------------------------------------------------


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

    Returns:
      list of T (H, W, 3) uint8 images.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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


def write_gif(path: Path, images: list[np.ndarray], fps: float = 8.0) -> None:
    """Animated GIF of equally sized RGB frames, written atomically."""
    import imageio.v3 as iio

    data = iio.imwrite("<bytes>", np.stack(images), extension=".gif", duration=1000 / fps, loop=0)
    with atomic.writer(path, "wb") as f:
        f.write(data)


def write_strip(path: Path, images: list[np.ndarray], columns: int = 6) -> None:
    """PNG of `columns` frames spread over the sequence, stacked vertically, atomically."""
    import imageio.v3 as iio

    idx = np.unique(np.linspace(0, len(images) - 1, columns).astype(int))
    buffer = _io.BytesIO()
    iio.imwrite(buffer, np.concatenate([images[i] for i in idx], axis=0), extension=".png")
    with atomic.writer(path, "wb") as f:
        f.write(buffer.getvalue())


def write_motion_pictures(
    stem: Path,
    motions: list[np.ndarray],
    labels: list[str],
    parents,
    clouds: list[np.ndarray | None] | None = None,
) -> None:
    """`stem`.gif (the whole motion) and `stem`.png (a strip of frames) of `render_frames`."""
    images = render_frames(motions, labels, parents, clouds=clouds)
    write_gif(stem.with_name(stem.name + ".gif"), images)
    write_strip(stem.with_name(stem.name + ".png"), images)
