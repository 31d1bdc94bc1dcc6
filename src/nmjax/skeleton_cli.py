"""`nmjax extract-skeleton --run RUN`: the phase-1 run's affinity -> `skeleton.json` + a picture.

Reads `<run>/affinity.npy` (N, K, K) and `<run>/keypoint_stats.npz` (contract C10), runs
Algorithm 1 (`nmjax.skeleton.extract_skeleton`; `--method filtered` for the variant) and writes
`<run>/skeleton.json` (parents, root, order, depth, method, intensities, rest_positions, pruned
parents) and `<run>/figures/skeleton.png` (the tree over the example frame's occupied voxels;
pruned low-intensity keypoints faded).
"""

from __future__ import annotations

import argparse
import io as _io
import os
import time
from pathlib import Path

import numpy as np

from nmjax import io
from nmjax.data.voxelize import voxel_points
from nmjax.skeleton import (
    DEFAULT_NEIGHBORS,
    METHODS,
    PRUNE_THRESHOLD,
    Skeleton,
    extract_skeleton,
    prune,
)

STATS_KEYS = ("intensities", "rest_positions", "example_voxels", "example_keypoints")


def read_run(run_dir: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(affinity (N, K, K), keypoint stats) of a phase-1 run, checked against each other.

    Raises:
      FileNotFoundError: a missing run folder or file (names the file and how it is made).
      ValueError: missing keys or shapes that disagree.
    """
    if not run_dir.is_dir():
        raise FileNotFoundError(f"phase-1 run folder {run_dir} does not exist (--run)")
    affinity_path, stats_path = run_dir / "affinity.npy", run_dir / "keypoint_stats.npz"
    for path in (affinity_path, stats_path):
        if not path.is_file():
            raise FileNotFoundError(
                f"{path} not found; phase-1 training (`nmjax train-skel`) writes it at the end"
            )
    affinity = np.load(affinity_path)
    if affinity.ndim == 2:
        affinity = affinity[None]
    if affinity.ndim != 3 or affinity.shape[1] != affinity.shape[2]:
        raise ValueError(f"{affinity_path} must hold an (N, K, K) array, got {affinity.shape}")
    num = affinity.shape[1]
    with np.load(stats_path) as z:
        missing = [k for k in STATS_KEYS if k not in z.files]
        if missing:
            raise ValueError(f"{stats_path} lacks {missing}; it needs {list(STATS_KEYS)}")
        stats = {k: np.asarray(z[k]) for k in STATS_KEYS}
    expected = {
        "intensities": (num,),
        "rest_positions": (num, 3),
        "example_keypoints": (num, 4),
    }
    for key, shape in expected.items():
        if stats[key].shape != shape:
            raise ValueError(
                f"{stats_path}: {key} has shape {stats[key].shape}, expected {shape} for the "
                f"K={num} keypoints of {affinity_path}"
            )
    if stats["example_voxels"].ndim != 3:
        raise ValueError(
            f"{stats_path}: example_voxels must be (G, G, G), got {stats['example_voxels'].shape}"
        )
    return affinity, stats


def extract_run_skeleton(
    run_dir: str | os.PathLike,
    n_neighbors: int | None = None,
    prune_threshold: float = PRUNE_THRESHOLD,
    method: str = "algorithm1",
) -> Skeleton:
    """Extracts, saves and draws the skeleton of a phase-1 run (called at the end of train-skel).

    Args:
      run_dir: phase-1 run folder with affinity.npy and keypoint_stats.npz (contract C10).
      n_neighbors: N of Algorithm 1; None uses `DEFAULT_NEIGHBORS` (2).
      prune_threshold: keypoints with mean intensity below it are drawn faded and listed as
        pruned (`pruned_parents`, `keep`); the tree itself spans all K keypoints.
      method: "algorithm1" (the paper's, default) or "filtered" (`extract_skeleton`).

    Returns:
      The `Skeleton` written to `<run_dir>/skeleton.json`.
    """
    run_dir = Path(run_dir)
    n_neighbors = DEFAULT_NEIGHBORS if n_neighbors is None else n_neighbors
    affinity, stats = read_run(run_dir)
    skeleton = extract_skeleton(affinity, n_neighbors, stats["intensities"], method=method)
    pruned, keep = prune(skeleton, stats["intensities"], prune_threshold)
    skeleton.save(
        run_dir / "skeleton.json",
        intensities=stats["intensities"].astype(np.float64),
        rest_positions=stats["rest_positions"].astype(np.float64),
        n_neighbors=int(n_neighbors),
        method=method,
        prune_threshold=float(prune_threshold),
        pruned_parents=list(pruned.parents),
        keep=keep.tolist(),
    )
    draw_skeleton(
        run_dir / "figures" / "skeleton.png",
        skeleton,
        stats["example_keypoints"],
        stats["example_voxels"],
        keep,
        title=f"{run_dir.name}: K={skeleton.num_keypoints}, kept {int(keep.sum())}",
    )
    return skeleton


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
    with io.atomic_open(path, "wb") as f:
        f.write(buffer.getvalue())


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="nmjax extract-skeleton",
        description="Turn a phase-1 run's learned affinity into a kinematic tree (Algorithm 1).",
    )
    parser.add_argument("--run", required=True, metavar="RUN", help="phase-1 run folder")
    parser.add_argument(
        "--neighbors",
        type=int,
        default=DEFAULT_NEIGHBORS,
        metavar="N",
        help=f"maximum neighbours per keypoint (default {DEFAULT_NEIGHBORS})",
    )
    parser.add_argument(
        "--prune-threshold",
        type=float,
        default=PRUNE_THRESHOLD,
        metavar="ALPHA",
        help=f"keypoints with mean intensity below it are pruned (default {PRUNE_THRESHOLD})",
    )
    parser.add_argument(
        "--method",
        choices=METHODS,
        default="algorithm1",
        help="algorithm1: the paper's Algorithm 1 (default); filtered: weak links dropped first",
    )
    args = parser.parse_args(argv)
    start = time.perf_counter()
    skeleton = extract_run_skeleton(args.run, args.neighbors, args.prune_threshold, args.method)
    seconds = time.perf_counter() - start
    print(
        f"{Path(args.run) / 'skeleton.json'}: K={skeleton.num_keypoints}, root {skeleton.root}, "
        f"depth {skeleton.depth}, parents {list(skeleton.parents)} ({seconds:.2f} s with figure)"
    )
    return 0
