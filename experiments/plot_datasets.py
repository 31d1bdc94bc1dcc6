"""One frame of each built-in synthetic body: surface points and ground-truth bones.

    .venv/bin/python experiments/plot_datasets.py [--out experiments/figures/synthetic_datasets.png]

Each panel draws a subsample of the 20,000 surface points of one posed frame and a line from
every ground-truth joint to its parent. Nothing is written under data/: the sequences are
simulated in memory with `nmjax.data.synthetic.simulate`. The PNG carries the commit and machine
that drew it (`nmjax.provenance`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from nmjax import provenance
from nmjax.data import bodies, synthetic
from nmjax.viz import save_figure  # importing nmjax.viz selects the Agg backend

NAMES = ("synth-hand", "synth-arm", "synth-human", "synth-quadruped")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--out", type=Path, default=Path("experiments/figures/synthetic_datasets.png")
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frame", type=int, default=20, help="frame of a 40-frame motion")
    parser.add_argument("--shown-points", type=int, default=5000)
    args = parser.parse_args(argv)
    stamp = provenance.stamp()
    fig = plt.figure(figsize=(10, 10))
    rng = np.random.default_rng(args.seed)
    for panel, name in enumerate(NAMES):
        body = bodies.get_body(name)
        sequence = synthetic.simulate(name, 40, rng=args.seed + panel)
        points = sequence.vertices[args.frame]
        points = points[rng.choice(len(points), args.shown_points, replace=False)]
        joints = sequence.joints[args.frame]
        ax = fig.add_subplot(2, 2, panel + 1, projection="3d")
        ax.scatter(*points.T, s=1.5, c=points[:, 2], cmap="viridis", alpha=0.6, linewidths=0)
        for child, parent in enumerate(body.parents):
            if child != parent:
                ax.plot(*np.stack([joints[child], joints[parent]]).T, color="crimson", lw=1.8)
        ax.scatter(*joints.T, s=12, color="black", depthshade=False)
        centre = (points.max(0) + points.min(0)) / 2
        half = (points.max(0) - points.min(0)).max() / 2
        ax.set(xlim=centre[0] + [-half, half], ylim=centre[1] + [-half, half])
        ax.set(zlim=centre[2] + [-half, half])
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=20, azim=-60)
        ax.set_title(f"{name}: {len(body.joints)} joints, frame {args.frame}")
        ax.tick_params(labelsize=6)
    save_figure(fig, args.out, dpi=110)
    provenance.stamp_png(args.out, stamp)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
