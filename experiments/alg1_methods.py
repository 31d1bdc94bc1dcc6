"""Algorithm 1 against the "filtered" variant on learned affinities, and their speed.

    JAX_PLATFORMS=cpu .venv/bin/python experiments/alg1_methods.py \
        --runs runs/study/synth-arm-base-s0 runs/study/synth-hand-base-s0 ...

For every phase-1 run folder (its `affinity.npy`, `keypoint_stats.npz` and a detector checkpoint)
both tree rules of `nmjax.skeleton.extract_skeleton` run on the learned affinity. Each keypoint
is labelled with the ground-truth joint it is most often nearest to over the test crops of
`nmjax evaluate` (`metrics.node_joints`); an edge of a tree is *plausible* when the labels of its
two keypoints are the same joint or joints one bone apart in the body's true tree (`meta.json`
parents): the share of plausible edges is `metrics.edge_precision` within one bone. Reported per
run and method: plausible edges over all K - 1 edges, over the edges of the pruned tree (kept
nodes, mean alpha >= 0.2, re-attached to their nearest kept ancestor), the parents that differ
between the methods, and the median extraction time (with K = 28 random affinities as well).
Writes experiments/results/alg1_methods_runs.{md,json} (alg1_methods.{md,json} are
phase1_tables.py's; this script's earlier results are in results/archive/alg1_methods.*),
stamped with the commit, machine and metric definitions (`nmjax.provenance`).
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from nmjax import metrics, provenance
from nmjax.data.layout import read_meta
from nmjax.evaluate import phase1_outputs
from nmjax.run_folder import AFFINITY_FILE, STATS_FILE
from nmjax.skeleton import METHODS, extract_skeleton, prune
from nmjax.train.trained import Detector

RESULTS = Path(__file__).parent / "results"
METRICS = {
    "plausible_all": "share of the tree's K - 1 edges whose two keypoints' labels (the "
    "ground-truth joint each is most often nearest to over the test crops) are the same joint "
    "or one bone apart",
    "plausible_pruned": "the same over the edges between kept nodes (mean alpha >= 0.2)",
    "parents_differ": "keypoints whose parent differs between the two methods",
    "ms": "median wall time of one extract_skeleton call on this machine",
}


def crop_frames(detector: Detector, max_crops: int) -> tuple[np.ndarray, np.ndarray]:
    """(F, K, 4) keypoints and (F, J, 3) ground-truth joints of every frame of the test crops."""
    keypoints, joints = [], []
    for _, _, gt, kp, _ in phase1_outputs(detector, max_crops):
        keypoints.append(kp.reshape(-1, *kp.shape[-2:]))
        joints.append(gt.reshape(-1, *gt.shape[-2:]))
    return np.concatenate(keypoints), np.concatenate(joints)


def plausible(
    keypoints: np.ndarray, joints: np.ndarray, kept: np.ndarray, parents, true_parents
) -> float:
    """`metrics.edge_precision` (within one bone) of the tree `parents` over the `kept` nodes."""
    return float(metrics.edge_precision(keypoints, joints, kept, parents, true_parents))


def median_ms(affinity: np.ndarray, method: str, repeats: int = 200) -> float:
    extract_skeleton(affinity, method=method)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        extract_skeleton(affinity, method=method)
        times.append(time.perf_counter() - start)
    return float(np.median(times) * 1e3)


def evaluate_run(run: Path, max_crops: int) -> dict:
    affinity = np.load(run / AFFINITY_FILE)
    with np.load(run / STATS_FILE) as stats:
        intensities = np.asarray(stats["intensities"])
    detector = Detector.load(run)
    true_parents = read_meta(detector.cfg.data.name, detector.cfg.data.root)["parents"]
    keypoints, joints = crop_frames(detector, max_crops)
    out = {"run": str(run), "data": detector.cfg.data.name, "K": int(affinity.shape[-1])}
    every = np.ones(affinity.shape[-1], bool)
    trees = {}
    for method in METHODS:
        skeleton = extract_skeleton(affinity, method=method)
        pruned, keep = prune(skeleton, intensities)
        trees[method] = skeleton.parents
        out[method] = {
            "parents": list(skeleton.parents),
            "root": skeleton.root,
            "depth": skeleton.depth,
            "plausible_all": plausible(keypoints, joints, every, skeleton.parents, true_parents),
            "plausible_pruned": plausible(keypoints, joints, keep, pruned.parents, true_parents),
            # kept nodes hang off kept nodes (`prune`): every kept non-root node has one edge
            "pruned_edges": int(np.sum(keep)) - 1,
            "ms": median_ms(affinity, method),
        }
    out["parents_differ"] = int(np.sum(np.array(trees["algorithm1"]) != trees["filtered"]))
    out["labels"] = np.asarray(metrics.node_joints(keypoints, joints)).tolist()
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", nargs="+", required=True, type=Path)
    parser.add_argument("--max-crops", type=int, default=8)
    args = parser.parse_args()
    stamp = provenance.stamp(METRICS)
    rows = [evaluate_run(run, args.max_crops) for run in args.runs]
    rng = np.random.default_rng(0)
    random28 = {
        m: float(np.median([median_ms(rng.random((2, 28, 28)), m, 50) for _ in range(5)]))
        for m in METHODS
    }
    command = "JAX_PLATFORMS=cpu .venv/bin/python " + shlex.join(sys.argv)
    provenance.write_json(
        RESULTS / "alg1_methods_runs.json",
        {"command": command, "runs": rows, "random28_ms": random28},
        stamp,
    )
    lines = [
        "# Algorithm 1 against the filtered variant on learned affinities",
        "",
        f"Command: `{command}`",
        "",
        "Plausible edge: its two keypoints are labelled (most often nearest, test crops) with the",
        "same ground-truth joint or joints one bone apart. all: every edge of the tree over K",
        "keypoints; pruned: edges between kept nodes (mean alpha >= 0.2). ms: median extraction",
        "time on this machine.",
        "",
        "| run | K | method | root | depth | plausible (all) | plausible (pruned, edges) | ms |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        for method in METHODS:
            m = r[method]
            lines.append(
                f"| {r['run']} | {r['K']} | {method} | {m['root']} | {m['depth']} | "
                f"{m['plausible_all']:.2f} | {m['plausible_pruned']:.2f} ({m['pruned_edges']}) "
                f"| {m['ms']:.2f} |"
            )
    lines += ["", "Parents that differ between the two methods:", ""]
    lines += [f"- {r['run']}: {r['parents_differ']} of {r['K']}" for r in rows]
    lines += [
        "",
        "K = 28, random affinities (2, 28, 28), median over 5 x 50 calls: "
        + ", ".join(f"{m} {v:.3f} ms" for m, v in random28.items()),
        "",
    ]
    provenance.write_markdown(RESULTS / "alg1_methods_runs.md", "\n".join(lines), stamp)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
