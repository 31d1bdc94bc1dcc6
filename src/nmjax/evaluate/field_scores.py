"""The field's scores of a phase-1 run on its test crops, beside SC (`nmjax.metrics.rig_scores`):

- the tree edit distance of the kept tree (skeleton.json's `pruned_parents` and `keep`) to the
  true tree of the dataset's meta.json;
- CD-J2J, CD-J2B and CD-B2B of the kept nodes against the true joints, in every frame, both in
  that frame's body box scaled to [-0.5, 0.5]^3, x1e-2;
- the fit error of the rig `nmjax export` builds from the run (the kept nodes as joints, the
  crop's frame 0 as rest pose, swing rotations from the keypoints' bones,
  `nmjax.export.sources.positions_rig`) with Algorithm 2's skin weights on the crop's frame-0
  points: that surface skinned by the rig against every frame's points (at most `FIT_POINTS`
  of them, the same indices in every frame).

Every score is the mean over a sequence's crops and frames, then the mean and 95% CI over the
test sequences (the tree edit distance is one number a run).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from nmjax import metrics
from nmjax.evaluate.stats import summarize
from nmjax.export.rig import Rig
from nmjax.export.sources import kept_skin_weights, positions_rig

# results.json's names of the per-sequence scores, in the tables' order.
SKELETON_CD_KEYS = ("cd_j2j", "cd_j2b", "cd_b2b")
FIT_KEYS = ("rig_fit_cd", "rig_fit_cd_capture")
# Points of a crop the fit error compares, at most: the same fixed subset of point indices in
# every frame (so a capture whose points correspond across frames, a mesh's vertices, keeps its
# correspondence). The Chamfer between two 20,000-point frames costs about 3 s on 2 CPU cores,
# between two 4,096-point ones 0.2 s; where every frame samples its surface anew the value
# includes the sampling's own Chamfer, which is larger the fewer the points.
FIT_POINTS = 4096


def crop_rig(
    keypoints: np.ndarray,
    surface: np.ndarray,
    skeleton: tuple[np.ndarray, np.ndarray],
    frame_rate: float,
) -> tuple[Rig, np.ndarray]:
    """The rig of one crop as `nmjax export` builds it from a phase-1 run, and its skin weights.

    Args:
      keypoints: (T, K, 4) the detector's keypoints of the crop.
      surface: (V, 3) the crop's frame-0 points (the rest surface).
      skeleton: (pruned parents (K,), kept nodes (K,) bool), `run_folder.pruned_skeleton`.
      frame_rate: the motion's frames per second (recorded in the rig).

    Returns:
      the rig (J kept joints, rest pose frame 0, swing-only rotations) and its (V, J) skin
      weights: Algorithm 2 (`skeleton.skin_weights`) over the kept nodes at frame 0.
    """
    parents, keep = skeleton
    rig = positions_rig("crop", keypoints, parents, keep, frame_rate)
    return rig, kept_skin_weights(surface, keypoints[0], parents, keep)


def skinned_surface(rig: Rig, surface: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(T, V, 3): `surface` (V, 3) in the rig's rest pose, skinned with `weights` (V, J) and
    driven by the rig's motion. Joint k moves the rest pose to frame t by
    v -> R_k,t R_k,rest^T (v - mu_k,rest) + mu_k,t, blended by the weights: the linear blend
    skinning a retargeted mesh is deformed with (`nmjax.tasks.retarget_vertices`)."""
    from nmjax.tasks import retarget_vertices

    return np.asarray(
        retarget_vertices(
            surface,
            weights,
            rig.rest_positions,
            rig.rest_rotations,
            rig.positions,
            rig.rotations,
        )
    )


def fit_subset(num_points: int, limit: int = FIT_POINTS) -> np.ndarray:
    """The point indices the fit error compares: all of them up to `limit`, else `limit` of them
    drawn once with a fixed seed (the same for every crop of that size), in increasing order."""
    if num_points <= limit:
        return np.arange(num_points)
    return np.sort(np.random.default_rng(0).choice(num_points, limit, replace=False))


def crop_fit_error(
    keypoints: np.ndarray,
    points: np.ndarray,
    box_scale: float,
    skeleton: tuple[np.ndarray, np.ndarray],
    frame_rate: float,
    limit: int = FIT_POINTS,
) -> dict[str, float]:
    """`metrics.rig_fit_error` of one crop's rig (`crop_rig`): its frame-0 points skinned by the
    rig against each of its frames, on the points `fit_subset` picks.

    Args:
      keypoints: (T, K, 4); points: (T, N, 3) the crop in the normalised cube; box_scale: the
      crop's normalisation factor (`nmjax.data.normalize.normalization_box`); limit: points
      compared at most.

    Returns:
      {"cd": x1e4 in the cube, "cd_capture": in the capture's units, squared}.
    """
    points = np.asarray(points)[:, fit_subset(points.shape[1], limit)]
    rig, weights = crop_rig(keypoints, points[0], skeleton, frame_rate)
    return metrics.rig_fit_error(skinned_surface(rig, points[0], weights), points, box_scale)


def sequence_scores(
    crop: dict[str, Any],
    skeleton: tuple[np.ndarray, np.ndarray],
    true_parents: np.ndarray | None,
    frame_rate: float,
) -> dict[str, float]:
    """One test sequence's scores: each the mean over its crops (and their frames).

    Args:
      crop: {"points" (C, T, N, 3) in the cube, "box_scale" (C,), "keypoints" (C, T, K, 4),
        "joints" (C, T, J, 3) or None}, the sequence's crops (`nmjax.evaluate.phase1`).
      skeleton: (pruned parents (K,), kept nodes (K,) bool).
      true_parents: (J,) the true tree, or None.
      frame_rate: the run's frames per second.

    Returns:
      {"rig_fit_cd", "rig_fit_cd_capture"}, with "cd_j2j" where the sequence has joints and
      "cd_j2b", "cd_b2b" where the true tree is known too.
    """
    fits = [
        crop_fit_error(kp, pts, float(scale), skeleton, frame_rate)
        for kp, pts, scale in zip(crop["keypoints"], crop["points"], crop["box_scale"], strict=True)
    ]
    out = {
        "rig_fit_cd": float(np.mean([f["cd"] for f in fits])),
        "rig_fit_cd_capture": float(np.mean([f["cd_capture"] for f in fits])),
    }
    if crop["joints"] is not None:
        parents, keep = skeleton
        chamfers = metrics.skeleton_chamfers(
            crop["keypoints"][..., :3],
            parents,
            crop["joints"],
            true_parents,
            crop["points"],
            kept=keep,
        )
        out |= {key: float(np.mean(np.asarray(value))) for key, value in chamfers.items()}
    return out


def field_scores(
    per_sequence: dict[str, dict[str, float]],
    skeleton: tuple[np.ndarray, np.ndarray],
    true_parents: np.ndarray | None,
) -> dict[str, Any]:
    """The scores of the module docstring over the test sequences.

    Args:
      per_sequence: {sequence name: `sequence_scores`}.
      skeleton: (pruned parents (K,), kept nodes (K,) bool).
      true_parents: (J,) the true tree, or None (no tree edit distance).

    Returns:
      every key of `sequence_scores` that some sequence has, as {"mean", "ci95", "n",
      "per_sequence"} over the sequences that have it, and "tree_edit_distance" (an integer)
      with the true tree.
    """
    out: dict[str, Any] = {}
    for key in (*SKELETON_CD_KEYS, *FIT_KEYS):
        found = {name: s[key] for name, s in per_sequence.items() if key in s}
        if found:
            out[key] = {**summarize(list(found.values())), "per_sequence": found}
    if true_parents is not None:
        parents, keep = skeleton
        out["tree_edit_distance"] = metrics.tree_edit_distance(parents, true_parents, keep)
    return out
