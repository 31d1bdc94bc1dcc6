"""Where the SC-score of a phase-1 run is lost, and how precise keypoints must be for a target.

    .venv/bin/python experiments/sc_diagnostics.py --run runs/skel-synth-arm-cpu [--oracle-only]

On the test crops that `nmjax evaluate` uses (up to 8 per sequence, normalised per crop):

- the SC-score (Eq. 21), the skeleton nodes and, per ground-truth joint, its three most frequent
  nearest nodes with their share of the frames (`p_j(k)`);
- per node, the joint it is most often nearest to and the spread (std over frames, per axis) of
  its offset from that joint: a node attached to a rigid part near the joint keeps a small spread;
- the noise oracle: the SC-score of the ground-truth joints themselves, less one when J > K,
  perturbed by isotropic gaussian noise of each given std, i.e. how much keypoint jitter Eq. 21
  tolerates on this body.

Prints a report, headed by the commit, machine and definitions (`nmjax.provenance`); writes
nothing.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from nmjax import metrics, provenance
from nmjax.data.layout import read_meta
from nmjax.evaluate import phase1_outputs
from nmjax.train.trained import Detector

NOISE_STDS = (0.0, 0.02, 0.04, 0.06, 0.08)
METRICS = {
    "SC": "Eq. 21 as published (nmjax.metrics.SemanticConsistency) on the test crops",
    "p_j(k)": "share of the test frames in which node k is joint j's nearest node",
    "noise oracle": "SC of the ground-truth joints plus isotropic gaussian noise of std s",
}


def test_keypoints(detector: Detector, max_crops: int) -> tuple[np.ndarray, np.ndarray]:
    """Detected keypoints (F, K, 4) and ground-truth joints (F, J, 3) of every test frame."""
    keypoints, joints = [], []
    for name, _, gt, kp, _ in phase1_outputs(detector, max_crops):
        if gt is None:
            raise SystemExit(
                f"{detector.cfg.data.name}: sequence {name} has no ground-truth joints"
            )
        keypoints.append(kp.reshape(-1, *kp.shape[-2:]))
        joints.append(gt.reshape(-1, *gt.shape[-2:]))
    return np.concatenate(keypoints), np.concatenate(joints)


def noise_oracle(joints: np.ndarray, k: int, stds=NOISE_STDS, seed: int = 0) -> dict[float, float]:
    """SC-score of the first min(K, J) ground-truth joints plus gaussian noise, per noise std."""
    rng = np.random.default_rng(seed)
    pinned = joints[:, : min(k, joints.shape[1])]
    out = {}
    for std in stds:
        noisy = pinned + rng.normal(0.0, std, pinned.shape)
        kp = np.concatenate([noisy, np.ones((*noisy.shape[:-1], 1))], axis=-1)
        out[std] = metrics.semantic_consistency(kp.astype(np.float32), joints)
    return out


def report(run: Path, max_crops: int, oracle_only: bool) -> None:
    detector = Detector.load(run)
    cfg = detector.cfg
    names = read_meta(cfg.data.name, cfg.data.root)["joint_names"]
    kp, gt = test_keypoints(detector, max_crops)
    print(f"{run}: {kp.shape[0]} test frames, K={kp.shape[1]}, J={gt.shape[1]}")
    print("noise oracle (SC of the joints + gaussian noise of std s):")
    for std, score in noise_oracle(gt, kp.shape[1]).items():
        print(f"  s={std:.2f}: {score:.3f}")
    if oracle_only:
        return
    sc = metrics.SemanticConsistency()
    sc.update(kp, gt)
    counts, frames = sc.counts()
    nodes = np.flatnonzero(np.asarray(metrics.skeleton_nodes(kp)))
    print(f"SC {sc.result():.3f}; {len(nodes)} nodes: {nodes.tolist()}")
    print("per joint: max_k p_j(k), then its three most frequent nearest nodes")
    for j, name in enumerate(names):
        top = np.argsort(-counts[j])[:3]
        shares = "  ".join(f"k{k} {counts[j, k] / frames:.2f}" for k in top if counts[j, k] > 0)
        print(f"  {name:16s} {counts[j].max() / frames:.2f}   {shares}")
    dist = np.linalg.norm(kp[:, nodes, None, :3] - gt[:, None], axis=-1)  # (F, nodes, J)
    nearest = dist.argmin(-1)  # (F, nodes)
    print("per node: its most frequent nearest joint, share, offset std (x, y, z)")
    for i, k in enumerate(nodes):
        j = np.bincount(nearest[:, i], minlength=gt.shape[1]).argmax()
        share = np.mean(nearest[:, i] == j)
        spread = np.std(kp[:, k, :3] - gt[:, j], axis=0)
        print(f"  k{k:<3d} {names[j]:16s} {share:.2f}   {np.array2string(spread, precision=3)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True, type=Path, help="phase-1 run folder")
    parser.add_argument("--max-crops", type=int, default=8, help="test crops per sequence")
    parser.add_argument("--oracle-only", action="store_true", help="skip the per-joint tables")
    args = parser.parse_args()
    print(provenance.markdown(provenance.stamp(METRICS)))
    report(args.run, args.max_crops, args.oracle_only)


if __name__ == "__main__":
    main()
