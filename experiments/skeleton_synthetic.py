"""Skeleton extraction on a synthetic body without a trained detector (a stand-in phase-1 run).

Until a phase-1 run exists this checks Algorithm 1 end to end on data: a small synthetic set is
generated, its ground-truth joints play the keypoints, and the affinity is computed from motion
alone (no use of the true tree): keypoints that stay at a short, constant distance over time
are affine, A_ij proportional to exp(-(mean_t d_ij + 4 std_t d_ij) / tau), row-softmaxed like the
learned one. The script writes a C10-style run folder, runs `extract_run_skeleton`, prints the
extraction time and how many extracted edges are true bones, and copies the figure (stamped
with the commit and machine, `nmjax.provenance`).

    .venv/bin/python experiments/skeleton_synthetic.py --data synth-hand
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from nmjax import atomic, provenance
from nmjax.data.normalize import normalize_sequence
from nmjax.data.synthetic import generate
from nmjax.data.voxelize import voxelize
from nmjax.run_folder import AFFINITY_FILE, FIGURES_DIR, STATS_FILE
from nmjax.skeleton import extract_skeleton
from nmjax.train.trained import extract_run_skeleton


def motion_affinity(joints: np.ndarray, tau: float = 0.05) -> np.ndarray:
    """(K, K) row-softmaxed affinity from (T, K, 3) trajectories: short, rigid pairs are affine."""
    d = np.linalg.norm(joints[:, :, None] - joints[:, None], axis=-1)  # (T, K, K)
    logits = -(d.mean(axis=0) + 4.0 * d.std(axis=0)) / tau
    np.fill_diagonal(logits, -np.inf)
    a = np.exp(logits - logits.max(axis=1, keepdims=True))
    return a / a.sum(axis=1, keepdims=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="synth-hand")
    parser.add_argument("--grid", type=int, default=32)
    parser.add_argument("--out", default="experiments/figures")
    args = parser.parse_args()
    stamp = provenance.stamp(
        {"true bones": "extracted edges whose two joints are a bone of the generator's tree"}
    )
    with tempfile.TemporaryDirectory() as tmp:
        root = generate(args.data, Path(tmp) / args.data, num_sequences=2, frames=40, points=4000)
        meta = json.loads((root / "meta.json").read_text())
        seq = sorted((root / "train" / "vertices").glob("*.npy"))[0]
        points, joints = normalize_sequence(
            np.load(seq), np.load(root / "train" / "joints" / seq.name)
        )
        affinity = motion_affinity(joints)[None]
        num = joints.shape[1]
        run = Path(tmp) / f"skel-{args.data}-demo"
        atomic.save_npy(run / AFFINITY_FILE, affinity.astype(np.float32))
        keypoints = np.concatenate([joints[0], np.ones((num, 1))], axis=1).astype(np.float32)
        atomic.save_npz(
            run / STATS_FILE,
            intensities=np.ones(num, np.float32),
            rest_positions=joints.mean(axis=0).astype(np.float32),
            example_voxels=voxelize(points[0], args.grid),
            example_keypoints=keypoints,
        )
        extract_skeleton(affinity)
        start = time.perf_counter()
        for _ in range(100):
            extract_skeleton(affinity)
        ms = (time.perf_counter() - start) * 10
        skeleton = extract_run_skeleton(run)
        true = {tuple(sorted((k, p))) for k, p in enumerate(meta["parents"]) if k != p}
        found = {tuple(sorted(e)) for e in skeleton.edges()}
        print(
            f"{args.data}: K={num}, extraction {ms:.2f} ms, root {skeleton.root} "
            f"({meta['joint_names'][skeleton.root]}), {len(found & true)}/{len(true)} edges are "
            f"true bones, depth {skeleton.depth}"
        )
        out = Path(args.out) / f"skeleton_{args.data}.png"
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(run / FIGURES_DIR / "skeleton.png", out)
        provenance.stamp_png(out, stamp)
        print(f"figure: {out}")


if __name__ == "__main__":
    main()
