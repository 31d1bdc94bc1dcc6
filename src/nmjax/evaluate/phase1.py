"""Phase-1 evaluation on the test split: SC-score (Eq. 21, Table 1) in both definitions, 4D-tracking
Chamfer x1e4 (Table 2), bone-length variation of the pruned skeleton, the skeleton against the
ground truth and the field's scores (tree edit distance, CD-J2J / J2B / B2B, the rig's fit error),
on test crops of T frames each normalised on its own, as in training.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from nmjax import metrics, run_folder
from nmjax.config import frame_rate
from nmjax.evaluate.field_scores import (
    FIT_KEYS,
    FIT_POINTS,
    SKELETON_CD_KEYS,
    field_scores,
    sequence_scores,
)
from nmjax.evaluate.stats import summarize
from nmjax.evaluate.tables import SKELETON_TRUTH_COLUMNS
from nmjax.train.trained import Detector

# One line per measure of results.json, recorded in every results file (`nmjax.provenance`).
PHASE1_METRICS = {
    "sc": "SC-score, Eq. 21 as published: in each frame keypoints with alpha < 0.2 are no "
    "candidates for a joint's nearest keypoint; counts over all test frames (Table 1)",
    "sc_fixed_nodes": "Eq. 21 over the fixed node set of the pruned skeleton in every frame",
    "tracking": "4D-tracking Chamfer x1e4 (Table 2): reconstruction thresholded at 0.5 against "
    "the crop's voxels, mean per sequence; mean and 95% CI over test sequences",
    "bone_length_variation": "std / mean of each bone's length of the pruned skeleton over a "
    "crop of T frames, mean over bones and crops",
    "joint_distance": "mean distance from a ground-truth joint to its nearest kept node (cube "
    "[-1, 1]^3), mean over joints and frames per sequence; mean and 95% CI over sequences",
    "joint_coverage_0.05, joint_coverage_0.10": "share of joint-frames with a kept node within "
    "0.05 (0.10)",
    "edge_precision": "share of skeleton edges whose nodes' joints are the same or adjacent in "
    f"the true tree (edge_precision_within_{metrics.TWO_HOPS}_hops: within two hops)",
    "bone_recall": "share of true bones whose joints' nodes are the same or adjacent in the "
    "skeleton",
    "distinct_nodes": "kept nodes that are some joint's most frequent nearest kept node",
    "tree_edit_distance": "tree edit distance between the kept tree (skeleton.json's pruned tree "
    "over its kept nodes) and the dataset's true tree, rooted and unlabelled: APTED with insert "
    "1, delete 1, rename 0, every node's children ordered by the shape of their subtrees "
    "(Reart, AutoURDF)",
    "cd_j2j": "CD-J2J x1e-2 (RigNet, as MagicArticulate evaluates it): 1/2 (mean over kept nodes "
    "of the distance to the nearest true joint + mean over true joints of the distance to the "
    "nearest kept node), both in the frame's body box scaled to [-0.5, 0.5]^3; mean over frames "
    "per sequence; mean and 95% CI over sequences",
    "cd_j2b": "CD-J2B x1e-2: as CD-J2J, each joint's distance to the nearest bone segment of the "
    "other skeleton (the pruned tree's bones between kept nodes; the true tree's bones)",
    "cd_b2b": f"CD-B2B x1e-2: as CD-J2J, the mean along each skeleton's bones "
    f"({metrics.BONE_SAMPLES} midpoint samples a bone, weighted by its length) of the distance to "
    "the nearest bone segment of the other skeleton",
    "rig_fit_cd": "the rig's fit error, Chamfer of squared distances x1e4 in the cube (Table 2's "
    "units): each test crop's frame-0 points, skinned with Algorithm 2's weights by the rig "
    "`nmjax export` builds (the kept nodes, rest pose frame 0, swing rotations from the "
    "keypoints' bones; linear blend skinning), against the crop's points in every frame (at "
    f"most {FIT_POINTS}, the same point indices in every frame); mean over frames and crops per "
    "sequence; mean and 95% CI over sequences",
    "rig_fit_cd_capture": "the rig's fit error in the capture's units, squared: rig_fit_cd's "
    "Chamfer / s^2 (s the crop's normalisation factor, p' = s (p - bmin) - 1), unscaled",
}


def normalized_crops(seq, frames: int, sample_rate: int, max_crops: int):
    """Non-overlapping crops of one sequence (at most `max_crops`, spread over it), each
    normalised on its own like a training crop (`nmjax.data.normalize`).

    Returns:
      points (C, T, N, 3) in the cube, joints (C, T, J, 3) (None when the sequence has none)
      and each crop's normalisation factor s of p' = s (p - bmin) - 1, (C,).
    """
    from nmjax.data.datasets import crop_sequence, crop_span
    from nmjax.data.normalize import normalization_box, normalize_sequence

    span = crop_span(frames, sample_rate)
    starts = np.arange(0, max(seq.num_frames - span, 0) + 1, span)
    if len(starts) > max_crops:
        starts = starts[np.linspace(0, len(starts) - 1, max_crops).astype(int)]
    points, joints, scales = [], [], []
    for start in starts:
        raw, gt = crop_sequence(seq, frames, sample_rate, int(start))
        scales.append(float(normalization_box(raw)[1].reshape(())))
        normed, gt = normalize_sequence(raw, gt)
        points.append(normed)
        joints.append(gt)
    has_joints = all(j is not None for j in joints)
    return np.stack(points), (np.stack(joints) if has_joints else None), np.asarray(scales)


def phase1_crops(detector: Detector, max_crops: int = 8, split: str = "test"):
    """The detector on the crops of `normalized_crops`, one sequence of `split` at a time.

    Yields:
      {"name", "points" (C, T, N, 3) in the cube, "box_scale" (C,) the crops' normalisation
       factors, "voxels" (C, T, G, G, G), "joints" (C, T, J, 3) or None, "keypoints"
       (C, T, K, 4), "recon" (C, T, G, G, G)}.
    """
    from nmjax.data.datasets import load_sequences
    from nmjax.data.voxelize import voxelize

    cfg = detector.cfg
    for seq in load_sequences(cfg.data.name, split, cfg.data.root):
        points, joints, scales = normalized_crops(
            seq, cfg.data.frames, cfg.data.sample_rate, max_crops
        )
        voxels = np.stack([voxelize(p, cfg.data.grid) for p in points])
        keypoints, recon = detector.run_batches(voxels)
        yield {
            "name": seq.name,
            "points": points,
            "box_scale": scales,
            "voxels": voxels,
            "joints": joints,
            "keypoints": keypoints,
            "recon": recon,
        }


def phase1_outputs(detector: Detector, max_crops: int = 8, split: str = "test"):
    """`phase1_crops` as tuples, without the points.

    Yields:
      (sequence name, voxels (C, T, G, G, G), joints (C, T, J, 3) or None, keypoints
      (C, T, K, 4), reconstructions (C, T, G, G, G)).
    """
    for c in phase1_crops(detector, max_crops, split):
        yield c["name"], c["voxels"], c["joints"], c["keypoints"], c["recon"]


def true_tree(detector: Detector, num_joints: int) -> np.ndarray | None:
    """The ground-truth kinematic tree of the detector's dataset: the `parents` of its meta.json
    (read by `layout.read_meta`, which takes the root in any convention and returns it as its own
    parent), or None when the dataset does not record them.

    Raises:
      ValueError: the recorded parents are not a tree over the `num_joints` joints.
    """
    from nmjax.data.layout import dataset_root, read_meta

    data = detector.cfg.data
    parents = read_meta(data.name, data.root).get("parents")
    if parents is None:
        return None
    if len(parents) != num_joints:
        raise ValueError(
            f"{dataset_root(data.name, data.root) / 'meta.json'}: `parents` names {len(parents)} "
            f"joints but the joint files hold {num_joints}; regenerate or re-prepare the dataset"
        )
    return np.asarray(parents)


def skeleton_against_truth(
    keypoints: list[np.ndarray],
    joints: list[np.ndarray],
    skeleton: tuple[np.ndarray, np.ndarray],
    true_parents: np.ndarray | None,
    names: list[str],
) -> dict[str, Any]:
    """The skeleton measures of `metrics.skeleton_agreement` over every test frame, named as
    results.json names them.

    The joint distance is the mean over test sequences of each sequence's mean over its joints
    and frames (sequences weigh alike, as in the tracking Chamfer), with the 95% CI over
    sequences; the other measures pool all the frames (a node's joint and a joint's node are the
    most frequent over the whole test split).

    Args:
      keypoints: per sequence, (C, T, K, 4) keypoints of its crops.
      joints: per sequence, (C, T, J, 3) ground-truth joints of the same crops.
      skeleton: (pruned parents (K,), kept nodes (K,) bool), `run_folder.pruned_skeleton`.
      true_parents: (J,) the true tree, or None (edge precision and bone recall left out).
      names: the sequence names.

    Returns:
      {"joint_distance": {"mean", "ci95", "n", "per_sequence"}, "joint_coverage_0.05",
       "joint_coverage_0.10", "edge_precision", "edge_precision_within_2_hops", "bone_recall"
       (the last three only with `true_parents`), "distinct_nodes", "skeleton_kept_nodes"}.
    """
    parents, kept = skeleton
    per_seq = {
        name: float(metrics.joint_distance(kp, gt, kept))
        for name, kp, gt in zip(names, keypoints, joints, strict=True)
    }
    flat_kp = np.concatenate([kp.reshape(-1, *kp.shape[-2:]) for kp in keypoints])
    flat_gt = np.concatenate([gt.reshape(-1, *gt.shape[-2:]) for gt in joints])
    scores = metrics.skeleton_agreement(flat_kp, flat_gt, kept, parents, true_parents)
    scores["joint_distance"] = {**summarize(list(per_seq.values())), "per_sequence": per_seq}
    scores["skeleton_kept_nodes"] = int(kept.sum())
    return scores


def evaluate_phase1(detector: Detector, max_crops: int = 8, split: str = "test") -> dict:
    """SC-score (Table 1), 4D-tracking Chamfer x1e4 (Table 2), bone-length variation and the
    skeleton against the ground truth on `split`.

    SC is reported in both definitions (`metrics.SC_NODES`): "sc" is the published one
    (per-frame candidates with alpha >= 0.2), "sc_fixed_nodes" the fixed node set of the pruned
    skeleton. The bone-length variation (`metrics.bone_length_variation`) and the skeleton
    measures (`skeleton_against_truth`) take the pruned tree and kept nodes stored in the run's
    skeleton.json (`run_folder.pruned_skeleton`): the bones between kept nodes over the same crops
    (each crop one sequence of T frames), absent when the run has no skeleton yet; the skeleton
    against the true tree of the dataset's meta.json (`true_tree`), absent without ground-truth
    joints or a skeleton. The field's scores (`nmjax.evaluate.field_scores`: tree edit
    distance, CD-J2J / J2B / B2B and the rig's fit error) take the same skeleton and crops.

    Returns:
      {"sc": {"score", "std_over_joints", "per_sequence"}, "sc_fixed_nodes": {same} (both absent
       without ground-truth joints), "tracking": {"mean", "ci95", "n", "per_sequence"},
       "bone_length_variation": {"mean", "kept_nodes", "per_sequence"}, and the keys of
       `skeleton_against_truth` and of `field_scores`}.
    """
    sc = metrics.SemanticConsistency()
    per_seq_sc: dict[str, dict[str, float]] = {"per_frame": {}, "fixed": {}}
    per_seq_cd, per_seq_bones, all_keypoints = {}, {}, []
    truth: dict[str, list] = {"names": [], "keypoints": [], "joints": []}
    skeleton = run_folder.pruned_skeleton(detector.run)
    per_seq_field: dict[str, dict[str, float]] = {}
    true_parents, rate = None, frame_rate(detector.cfg.data.name, detector.cfg.data.sample_rate)
    for crops in phase1_crops(detector, max_crops, split):
        name, voxels, joints = crops["name"], crops["voxels"], crops["joints"]
        keypoints, recon = crops["keypoints"], crops["recon"]
        if joints is not None and not truth["names"]:  # the first sequence with joints
            true_parents = true_tree(detector, joints.shape[-2])
        if skeleton is not None:
            per_seq_field[name] = sequence_scores(crops, skeleton, true_parents, rate)
        per_seq_cd[name] = float(
            np.mean([metrics.tracking_chamfer(v, r) for v, r in zip(voxels, recon, strict=True)])
        )
        if joints is not None:
            sc.update(keypoints, joints)
            for nodes in metrics.SC_NODES:
                per_seq_sc[nodes][name] = metrics.semantic_consistency(
                    keypoints, joints, nodes=nodes
                )
            for key, value in (("names", name), ("keypoints", keypoints), ("joints", joints)):
                truth[key].append(value)
        if skeleton is not None:
            parents, kept = skeleton
            per_seq_bones[name] = float(
                metrics.bone_length_variation(keypoints, parents, kept=kept)
            )
            all_keypoints.append(keypoints)
    out: dict[str, Any] = {
        "tracking": {**summarize(list(per_seq_cd.values())), "per_sequence": per_seq_cd}
    }
    if sc.frames > 0:
        for key, nodes in (("sc", "per_frame"), ("sc_fixed_nodes", "fixed")):
            out[key] = {
                "score": sc.result(nodes),
                "std_over_joints": float(np.std(sc.per_joint(nodes))),
                "per_sequence": per_seq_sc[nodes],
            }
    if skeleton is not None and all_keypoints:
        parents, kept = skeleton
        out["bone_length_variation"] = {
            "mean": float(
                metrics.bone_length_variation(np.concatenate(all_keypoints), parents, kept=kept)
            ),
            "kept_nodes": int(kept.sum()),
            "per_sequence": per_seq_bones,
        }
    if skeleton is not None and truth["names"]:
        out.update(
            skeleton_against_truth(
                truth["keypoints"], truth["joints"], skeleton, true_parents, truth["names"]
            )
        )
    if skeleton is not None and per_seq_field:
        out.update(field_scores(per_seq_field, skeleton, true_parents))
    return out


def phase1_scores(results: dict) -> dict[str, float]:
    """The headline numbers of `evaluate_phase1`'s results, flat: "tracking_cd" and
    "tracking_cd_ci95"; "sc", "sc_fixed_nodes" and each one's "_std_over_joints" (with
    ground-truth joints); "bone_length_variation" (with a skeleton); "joint_distance" and
    "joint_distance_ci95" and the other skeleton measures (`SKELETON_TRUTH_COLUMNS`) with
    "skeleton_kept_nodes" (with joints and a skeleton); the field's scores (`field_scores`):
    "tree_edit_distance", "cd_j2j", "cd_j2b", "cd_b2b" (with joints and the true tree; CD-J2J
    with joints alone) and "rig_fit_cd", "rig_fit_cd_capture" (with a skeleton), each of the
    last five with its "_ci95"."""
    scores = {
        "tracking_cd": results["tracking"]["mean"],
        "tracking_cd_ci95": results["tracking"]["ci95"],
    }
    for key in ("sc", "sc_fixed_nodes"):
        if key in results:
            scores[key] = results[key]["score"]
            scores[f"{key}_std_over_joints"] = results[key]["std_over_joints"]
    if "bone_length_variation" in results:
        scores["bone_length_variation"] = results["bone_length_variation"]["mean"]
    if "joint_distance" in results:
        scores["joint_distance"] = results["joint_distance"]["mean"]
        scores["joint_distance_ci95"] = results["joint_distance"]["ci95"]
    for key in [k for k, _ in SKELETON_TRUTH_COLUMNS[1:]] + ["skeleton_kept_nodes"]:
        if key in results:
            scores[key] = results[key]
    if "tree_edit_distance" in results:
        scores["tree_edit_distance"] = results["tree_edit_distance"]
    for key in (*SKELETON_CD_KEYS, *FIT_KEYS):
        if key in results:
            scores[key] = results[key]["mean"]
            scores[f"{key}_ci95"] = results[key]["ci95"]
    return scores


# Occupied cells a picture frame keeps: enough to show the body's shape behind the skeleton.
PICTURE_POINTS = 1500


def picture_frame(detector: Detector, points: int = PICTURE_POINTS) -> dict[str, Any]:
    """One test frame for pictures of a run: the middle frame of the first test crop's
    keypoints (K, 4) and a fixed sample of `points` of its occupied cells, as lists (rounded to
    1e-4 and 1e-3: the cells' spacing is at least 1/32 of the cube), for a results row."""
    _, voxels, _, keypoints, _ = next(iter(phase1_outputs(detector, max_crops=1)))
    t = voxels.shape[1] // 2
    cells = metrics.voxel_points(voxels[0, t])
    if len(cells) > points:
        cells = cells[np.random.default_rng(0).choice(len(cells), points, replace=False)]
    return {
        "keypoints": np.round(keypoints[0, t], 4).tolist(),
        "points": np.round(cells, 3).tolist(),
    }
