"""The picture of an extracted skeleton (`nmjax.runs.extract_run_skeleton` draws it into
`<run>/figures/skeleton.png`): the tree over the example frame's occupied voxels, pruned
low-intensity keypoints faded.
"""

from __future__ import annotations

import io as _io
from pathlib import Path

import numpy as np

from nmjax import atomic
from nmjax.data.voxelize import voxel_points
from nmjax.skeleton import Skeleton


def draw_skeleton(
    path: Path,
    skeleton: Skeleton,
    keypoints: np.ndarray,
    voxels: np.ndarray,
    keep: np.ndarray,
    title: str = "",
) -> None:
    """Saves a 3D picture of the tree on `keypoints` (K, 4) over the occupied cells of `voxels`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    buffer = _io.BytesIO()
    fig.savefig(buffer, format="png", dpi=120, bbox_inches="tight")
    plt.close(fig)
    with atomic.writer(path, "wb") as f:
        f.write(buffer.getvalue())
