"""Measures of a discovered skeleton (docs/architecture.md §9): the bone-length variation of its
bones over time, and, on data with ground-truth joints, the skeleton against the true tree (joint
distance, joint coverage, edge precision, bone recall, distinct nodes).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array


def bone_lengths(keypoints: Array, parents: Array) -> Array:
    """Length of every keypoint's bone to its parent, ||mu_k - mu_parent(k)|| (0 at the root).

    Args:
        keypoints: (..., K, 4) or (..., K, 3) keypoints.
        parents: (K,) int parent of every keypoint (the root is its own parent).

    Returns:
        (..., K).
    """
    mu = keypoints[..., :3]
    return jnp.linalg.norm(mu - jnp.take(mu, jnp.asarray(parents), axis=-2), axis=-1)


def bone_length_variation(
    keypoints: Array,
    parents: Array,
    alpha_min: float = 0.2,
    eps: float = 1e-8,
    kept: Array | None = None,
) -> Array:
    """Bone-length variation E_b (docs/architecture.md §9): for every bone between kept nodes, the
    standard deviation over time of its length divided by its mean length, averaged over the bones
    and the sequences. 0 for a rigid skeleton whose bones keep their length.

    The kept nodes are the keypoints whose mean alpha over all the given frames is >=
    `alpha_min`, unless `kept` gives the node set (e.g. a run's pruned skeleton, whatever
    intensities generated motion carries); a bone (k, parent(k)) counts when both ends are kept.
    Pass the pruned tree (`skeleton.prune`, children re-attached to their nearest kept ancestor)
    to measure the bones of the pruned skeleton.

    Args:
        keypoints: (S, T, K, 4) sequences of keypoints, or one (T, K, 4) sequence; T >= 2.
        parents: (K,) int parents of the skeleton (the root is its own parent).
        alpha_min: node threshold on the mean intensity (0 keeps every keypoint).
        eps: added to the mean length (a bone of length 0 scores 0, not nan).
        kept: optional (K,) bool node set used instead of the mean-alpha threshold.

    Returns:
        scalar; nan when the skeleton has no bone between kept nodes.
    """
    kp = keypoints[None] if keypoints.ndim == 3 else keypoints
    if kp.ndim != 4 or kp.shape[-1] != 4 or kp.shape[1] < 2:
        raise ValueError(
            f"bone_length_variation: keypoints must be (S, T, K, 4) or (T, K, 4) with T >= 2, "
            f"got {keypoints.shape}"
        )
    parents = jnp.asarray(parents)
    if parents.shape != (kp.shape[-2],):
        raise ValueError(
            f"bone_length_variation: parents {parents.shape} do not match K={kp.shape[-2]}"
        )
    lengths = bone_lengths(kp, parents)  # (S, T, K)
    cv = jnp.std(lengths, axis=1) / (jnp.mean(lengths, axis=1) + eps)  # (S, K)
    if kept is None:
        kept = jnp.mean(kp[..., 3], axis=(0, 1)) >= alpha_min  # (K,)
    kept = jnp.asarray(kept, bool)
    bone = kept & kept[parents] & (parents != jnp.arange(kp.shape[-2]))  # (K,)
    n = jnp.sum(bone) * kp.shape[0]
    total = jnp.sum(jnp.where(bone[None], cv, 0.0))
    return jnp.where(n > 0, total / jnp.maximum(n, 1), jnp.nan)


# --- skeleton against the ground truth ---------------------------------------------------------

# SC (Eq. 21) asks only whether each joint keeps the same nearest keypoint: it rewards keypoints
# bunched in one place and cannot see a tree that links the wrong parts. These measures, for data
# with ground-truth joints (docs/architecture.md §9), ask where the kept nodes are and whether the
# skeleton's tree is the true one. Nodes and joints are matched by Euclidean distance in the
# normalised cube [-1, 1]^3. All are array math, jit- and vmap-able: the trees enter as adjacency
# matrices of their parent arrays (`tree_within`), so no graph library is needed.

COVERAGE_RADII = (0.05, 0.10)  # joint_coverage radii reported by `nmjax evaluate`
TWO_HOPS = 2  # the looser edge precision counts joints within two hops of each other


def _matched_frames(keypoints: Array, gt_joints: Array, kept: Array) -> tuple[Array, Array, Array]:
    """(F, K, 3) node positions, (F, J, 3) joints and (K,) bool kept nodes, checked."""
    kp, gt = jnp.asarray(keypoints), jnp.asarray(gt_joints)
    if kp.shape[:-2] != gt.shape[:-2] or kp.shape[-1] < 3 or gt.shape[-1] != 3:
        raise ValueError(
            f"keypoints {kp.shape} (..., K, C >= 3) and gt_joints {gt.shape} (..., J, 3) must "
            "describe the same frames (equal leading axes)"
        )
    kept = jnp.asarray(kept, bool)
    if kept.shape != kp.shape[-2:-1]:
        raise ValueError(
            f"kept nodes {kept.shape} must be a ({kp.shape[-2]},) bool mask over the K keypoints "
            "(skeleton.json's `keep`)"
        )
    k, j = kp.shape[-2], gt.shape[-2]
    return kp[..., :3].reshape(-1, k, 3), gt.reshape(-1, j, 3), kept


def _most_frequent(nearest: Array, distances: Array) -> Array:
    """For every row m, the column most often nearest over the frames; ties go to the column
    of smaller mean distance, so the answer does not depend on the order of the columns.

    Args:
        nearest: (F, M) int, the nearest column of row m in each frame.
        distances: (F, M, N) distances (inf for columns that never qualify).

    Returns:
        (M,) int.
    """
    counts = jnp.sum(jax.nn.one_hot(nearest, distances.shape[-1]), axis=0)  # (M, N)
    top = counts == jnp.max(counts, axis=-1, keepdims=True)
    return jnp.argmin(jnp.where(top, jnp.mean(distances, axis=0), jnp.inf), axis=-1)


def joint_to_node_distances(keypoints: Array, gt_joints: Array, kept: Array) -> Array:
    """Distance from every ground-truth joint to every node, inf for the nodes not kept.

    Args:
        keypoints: (..., K, C) detected keypoints (xyz first; C >= 3).
        gt_joints: (..., J, 3) ground-truth joints of the same frames (same normalisation).
        kept: (K,) bool, the skeleton's kept nodes.

    Returns:
        (F, J, K) with F the product of the leading axes.
    """
    mu, gt, kept = _matched_frames(keypoints, gt_joints, kept)
    d = jnp.linalg.norm(gt[:, :, None, :] - mu[:, None, :, :], axis=-1)
    return jnp.where(kept, d, jnp.inf)


def nearest_kept_distance(keypoints: Array, gt_joints: Array, kept: Array) -> Array:
    """(F, J) distance from every ground-truth joint to its nearest kept node in each frame
    (shapes as `joint_to_node_distances`)."""
    return jnp.min(joint_to_node_distances(keypoints, gt_joints, kept), axis=-1)


def joint_distance(keypoints: Array, gt_joints: Array, kept: Array) -> Array:
    """Mean over joints and frames of the distance from a ground-truth joint to its nearest kept
    node, in the units of the normalised cube [-1, 1]^3; 0 when a node sits on every joint.

    The joint-to-nearest-joint direction of the joint Chamfer distance that rigging work reports
    between predicted and true joints (e.g. RigNet's CD-J2J, Xu et al. 2020); the other direction
    (node to nearest joint) is left out, since the model may keep more nodes than the body has
    joints without being wrong.

    Args:
        keypoints: (..., K, C) detected keypoints (xyz first; C >= 3).
        gt_joints: (..., J, 3) ground-truth joints of the same frames.
        kept: (K,) bool kept nodes (at least one).

    Returns:
        scalar.
    """
    return jnp.mean(nearest_kept_distance(keypoints, gt_joints, kept))


def joint_coverage(keypoints: Array, gt_joints: Array, kept: Array, radius: float) -> Array:
    """Fraction of joint-frames whose nearest kept node lies within `radius` of the joint.

    PCK, the percentage of correct keypoints of pose estimation (Yang and Ramanan, PAMI 2013), with
    each joint matched to its nearest node instead of a named keypoint; `nmjax evaluate`
    reports it at `COVERAGE_RADII` (0.05 and 0.10 of the cube [-1, 1]^3). Keypoints bunched at
    one joint cover that joint only.

    Args:
        keypoints: (..., K, C) detected keypoints; gt_joints: (..., J, 3) joints of the same
            frames; kept: (K,) bool kept nodes.
        radius: distance threshold (inclusive), normalised units.

    Returns:
        scalar in [0, 1].
    """
    return jnp.mean(nearest_kept_distance(keypoints, gt_joints, kept) <= radius)


def joint_nodes(keypoints: Array, gt_joints: Array, kept: Array) -> Array:
    """Every ground-truth joint's node: the kept node most often its nearest over the frames
    (the argmax over k of Eq. 21's p_j(k) with the kept nodes as candidates); ties go to the
    node of smaller mean distance.

    Args:
        keypoints: (..., K, C); gt_joints: (..., J, 3); kept: (K,) bool.

    Returns:
        (J,) int node indices (all kept).
    """
    d = joint_to_node_distances(keypoints, gt_joints, kept)  # (F, J, K)
    return _most_frequent(jnp.argmin(d, axis=-1), d)


def node_joints(keypoints: Array, gt_joints: Array) -> Array:
    """Every node's joint: the ground-truth joint most often nearest to it over the frames; ties
    go to the joint of smaller mean distance.

    Args:
        keypoints: (..., K, C); gt_joints: (..., J, 3) joints of the same frames.

    Returns:
        (K,) int joint indices (computed for every node, kept or not).
    """
    mu, gt, _ = _matched_frames(keypoints, gt_joints, jnp.ones(keypoints.shape[-2], bool))
    d = jnp.linalg.norm(mu[:, :, None, :] - gt[:, None, :, :], axis=-1)  # (F, K, J)
    return _most_frequent(jnp.argmin(d, axis=-1), d)


def tree_within(parents: Array, hops: int) -> Array:
    """Which vertices of a tree lie at most `hops` edges apart.

    Args:
        parents: (N,) int parent of every vertex (the root is its own parent).
        hops: static int >= 0; 0: the same vertex, 1: the same or adjacent.

    Returns:
        (N, N) bool, symmetric.
    """
    parents = jnp.asarray(parents)
    n = parents.shape[0]
    link = jnp.zeros((n, n), jnp.float32).at[jnp.arange(n), parents].set(1.0)
    step = jnp.eye(n, dtype=jnp.float32) + link + link.T  # stay or cross one edge
    return jnp.linalg.matrix_power(step, hops) > 0


def edge_precision(
    keypoints: Array,
    gt_joints: Array,
    kept: Array,
    parents: Array,
    true_parents: Array,
    hops: int = 1,
) -> Array:
    """Fraction of skeleton edges whose two nodes' joints are the same or adjacent in the true
    tree (within `hops` edges of it; 1 by default, `TWO_HOPS` for the looser count).

    Each kept node stands for its joint (`node_joints`: the joint it is nearest to most often
    over the frames); an edge (k, parents[k]) counts when both ends are kept nodes. Two nodes on
    the same joint count as right: a bone the body does not have between them is not claimed.
    The precision half of comparing a discovered kinematic tree with the true one under a
    node-to-joint matching, the question tree edit distance answers in articulated-object
    discovery (Reart, CVPR 2023; AutoURDF, CVPR 2025). A skeleton linking the two ends of a
    chain scores below 1.

    Args:
        keypoints: (..., K, C); gt_joints: (..., J, 3); kept: (K,) bool.
        parents: (K,) int, the skeleton's tree over the K keypoints (the pruned tree of
            skeleton.json, `pruned_parents`: kept nodes hang off kept nodes).
        true_parents: (J,) int, the ground-truth tree (the root is its own parent).
        hops: static int, the largest true-tree distance that counts as right.

    Returns:
        scalar in [0, 1]; nan when no edge joins two kept nodes.
    """
    kept = jnp.asarray(kept, bool)
    parents = jnp.asarray(parents)
    joint = node_joints(keypoints, gt_joints)  # (K,)
    edge = kept & kept[parents] & (parents != jnp.arange(parents.shape[0]))
    right = tree_within(true_parents, hops)[joint, joint[parents]]
    n = jnp.sum(edge)
    return jnp.where(n > 0, jnp.sum(edge & right) / jnp.maximum(n, 1), jnp.nan)


def bone_recall(
    keypoints: Array, gt_joints: Array, kept: Array, parents: Array, true_parents: Array
) -> Array:
    """Fraction of ground-truth bones (j, true_parents[j]) whose two joints' nodes are the same
    node or adjacent in the skeleton.

    Each joint's node is `joint_nodes` (its most frequent nearest kept node); the recall half of
    the tree comparison of `edge_precision`. Keypoints bunched at one joint recall the bones
    whose both joints map onto the bunch and no others.

    Args:
        keypoints: (..., K, C); gt_joints: (..., J, 3); kept: (K,) bool.
        parents: (K,) int, the skeleton's pruned tree (`pruned_parents`).
        true_parents: (J,) int, the ground-truth tree.

    Returns:
        scalar in [0, 1]; nan for a tree of one joint.
    """
    true_parents = jnp.asarray(true_parents)
    node = joint_nodes(keypoints, gt_joints, kept)  # (J,)
    bone = true_parents != jnp.arange(true_parents.shape[0])
    right = tree_within(parents, 1)[node, node[true_parents]]
    n = jnp.sum(bone)
    return jnp.where(n > 0, jnp.sum(bone & right) / jnp.maximum(n, 1), jnp.nan)


def distinct_nodes(keypoints: Array, gt_joints: Array, kept: Array) -> Array:
    """How many kept nodes are some joint's node (`joint_nodes`): J when every joint has a node
    of its own, 1 when all the keypoints are bunched in one place (which SC does not see). The
    count behind the "distinct nearest keypoints" of the phase-1 study.

    Args:
        keypoints: (..., K, C); gt_joints: (..., J, 3); kept: (K,) bool.

    Returns:
        scalar int32 in [1, min(J, kept nodes)].
    """
    node = joint_nodes(keypoints, gt_joints, kept)
    return jnp.sum(jnp.zeros(keypoints.shape[-2], bool).at[node].set(True), dtype=jnp.int32)


@functools.partial(jax.jit, static_argnames=("radii",))
def _agreement(keypoints, gt_joints, kept, parents, true_parents, radii):
    scores = {"joint_distance": joint_distance(keypoints, gt_joints, kept)}
    for radius in radii:
        scores[f"joint_coverage_{radius:.2f}"] = joint_coverage(keypoints, gt_joints, kept, radius)
    if parents is not None and true_parents is not None:
        scores["edge_precision"] = edge_precision(keypoints, gt_joints, kept, parents, true_parents)
        scores[f"edge_precision_within_{TWO_HOPS}_hops"] = edge_precision(
            keypoints, gt_joints, kept, parents, true_parents, TWO_HOPS
        )
        scores["bone_recall"] = bone_recall(keypoints, gt_joints, kept, parents, true_parents)
    scores["distinct_nodes"] = distinct_nodes(keypoints, gt_joints, kept)
    return scores


def skeleton_agreement(
    keypoints: Array | np.ndarray,
    gt_joints: Array | np.ndarray,
    kept: Array | np.ndarray,
    parents: Array | np.ndarray | None = None,
    true_parents: Array | np.ndarray | None = None,
    radii: tuple[float, ...] = COVERAGE_RADII,
) -> dict[str, float]:
    """All the skeleton-against-truth measures of a set of frames, named as reports name them.

    Args:
        keypoints: (..., K, C) detected keypoints; gt_joints: (..., J, 3) joints of the same
            frames; kept: (K,) bool kept nodes.
        parents: (K,) the skeleton's pruned tree; true_parents: (J,) the true tree. The edge and
            bone measures need both and are left out without them.
        radii: the `joint_coverage` radii.

    Returns:
        {"joint_distance", "joint_coverage_<r>" per radius (two decimals: "joint_coverage_0.05"),
         "edge_precision", "edge_precision_within_2_hops", "bone_recall" (with both trees),
         "distinct_nodes"}; floats, and an int for distinct_nodes.
    """
    if true_parents is not None and np.shape(true_parents) != np.shape(gt_joints)[-2:-1]:
        raise ValueError(
            f"true parents {np.shape(true_parents)} do not match the J={np.shape(gt_joints)[-2]} "
            "ground-truth joints"
        )
    if parents is not None and np.shape(parents) != np.shape(keypoints)[-2:-1]:
        raise ValueError(
            f"skeleton parents {np.shape(parents)} do not match the K={np.shape(keypoints)[-2]} "
            "keypoints"
        )
    scores = _agreement(
        jnp.asarray(keypoints),
        jnp.asarray(gt_joints),
        jnp.asarray(kept, bool),
        None if parents is None else jnp.asarray(parents),
        None if true_parents is None else jnp.asarray(true_parents),
        tuple(float(r) for r in radii),
    )
    return {
        key: int(value) if key == "distinct_nodes" else float(value)
        for key, value in scores.items()
    }
