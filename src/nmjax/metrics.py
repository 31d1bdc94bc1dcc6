"""Evaluation metrics: SC-score (Eq. 21), bone-length variation, the skeleton against the ground
truth (joint distance, joint coverage, edge precision, bone recall, distinct nodes), the measures
of generated motion (diversity, set distance to real motion), Chamfer distances for 4D tracking
(Table 2) and M-CD (Eq. 22); DESIGN §9.

The numerical kernels (`nearest_keypoint_counts`, `chamfer_distance`) are pure and jit-able; the
front-ends (`SemanticConsistency`, `tracking_chamfer`, `motion_chamfer`) turn voxel grids into
point sets with NumPy (their sizes vary per frame) and pad them to a few bucket sizes so that the
compiled kernels are reused. Point sets of voxels are the occupied cells' coordinates on the
`linspace(-1, 1, G)` grid (`nmjax.data.voxelize.voxel_points`).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from nmjax.data.voxelize import voxel_points

MAX_SQ_DIST = 12.0  # squared diagonal of the normalised cube [-1, 1]^3: the worst possible CD term
TRACKING_SCALE = 1e4  # Table 2 reports the Chamfer distance x 1e4


# --- SC-score (Eq. 21) -------------------------------------------------------------------------

# How the candidates for "nearest keypoint" are chosen (DESIGN §9):
# "per_frame": the published SC-score: in every frame, the keypoints whose alpha in that frame is
#   >= the threshold. The default; what `nmjax evaluate` reports as "sc".
# "fixed": one node set over all the frames, the keypoints whose mean alpha is >= the threshold
#   (the pruned skeleton's nodes); reported beside it as "sc_fixed_nodes".
SC_NODES = ("per_frame", "fixed")


def skeleton_nodes(keypoints: Array, min_intensity: float = 0.2) -> Array:
    """The keypoints that are nodes of the pruned skeleton: mean intensity >= `min_intensity`.

    The intensity is averaged over all the given frames, so the node set is one fixed set, as
    the pruned skeleton of DESIGN §7 (alpha < 0.2 removed); the brightest keypoint always stays.

    Args:
        keypoints: (..., K, 4) detected keypoints.
        min_intensity: alpha threshold.

    Returns:
        (K,) bool.
    """
    mean_alpha = jnp.mean(keypoints[..., 3].reshape(-1, keypoints.shape[-2]), axis=0)
    return (mean_alpha >= min_intensity) | (mean_alpha == jnp.max(mean_alpha))


def _check_nodes(nodes: str) -> None:
    if nodes not in SC_NODES:
        raise ValueError(f"SC nodes must be one of {SC_NODES}, got {nodes!r}")


def nearest_keypoint_counts(
    keypoints: Array, gt_joints: Array, min_intensity: float = 0.2, nodes: str = "per_frame"
) -> tuple[Array, Array]:
    """How often each keypoint is the nearest candidate to each ground-truth joint (Eq. 21's
    p_j(k) times the number of frames).

    With `nodes="per_frame"` (the published SC-score, the default) a keypoint is a candidate in a
    frame when its alpha in that frame is >= `min_intensity`; a frame without any candidate
    counts for no keypoint (it still counts as a frame). With `nodes="fixed"` the candidates are
    the same in every frame, `skeleton_nodes` over all the given frames.

    Args:
        keypoints: (..., K, 4) detected keypoints, one set per frame.
        gt_joints: (..., J, 3) ground-truth joints of the same frames (same normalisation).
        min_intensity: the alpha threshold (DESIGN §9: 0.2).
        nodes: "per_frame" or "fixed" (`SC_NODES`).

    Returns:
        counts (J, K) float32 and the number of frames (scalar).
    """
    _check_nodes(nodes)
    k, j = keypoints.shape[-2], gt_joints.shape[-2]
    kp = keypoints.reshape(-1, k, 4)
    gt = gt_joints.reshape(-1, j, 3)
    if kp.shape[0] != gt.shape[0]:
        raise ValueError(
            f"keypoints {keypoints.shape} and gt_joints {gt_joints.shape} must describe the same "
            "frames (equal leading axes)"
        )
    if nodes == "fixed":
        candidate = jnp.broadcast_to(skeleton_nodes(kp, min_intensity), kp.shape[:2])  # (F, K)
    else:
        candidate = kp[..., 3] >= min_intensity  # (F, K)
    d = jnp.sum(jnp.square(gt[:, :, None, :] - kp[:, None, :, :3]), axis=-1)  # (F, J, K)
    d = jnp.where(candidate[:, None, :], d, jnp.inf)
    hits = jax.nn.one_hot(jnp.argmin(d, axis=-1), k)  # (F, J, K)
    hits = hits * jnp.any(candidate, axis=-1)[:, None, None]
    return jnp.sum(hits, axis=0), jnp.float32(kp.shape[0])


def sc_score_from_counts(counts: Array | np.ndarray, frames: float) -> float:
    """Eq. 21: SC = mean over joints j of max_k p_j(k), with p_j(k) = counts[j, k] / frames."""
    if frames <= 0:
        raise ValueError("semantic consistency: no frames given")
    return float(np.mean(np.max(np.asarray(counts), axis=-1)) / frames)


def semantic_consistency(
    keypoints: Array, gt_joints: Array, min_intensity: float = 0.2, nodes: str = "per_frame"
) -> float:
    """Eq. 21, the SC-score of a set of frames (see `SemanticConsistency` for many batches).

    The default is the published definition (per-frame candidates, counts accumulated over all
    the frames, p_j(k) = count / frames); `nodes="fixed"` counts the fixed node set of
    `skeleton_nodes` instead (see `nearest_keypoint_counts`).

    Args:
        keypoints: (F, K, 4) (any leading axes) detected keypoints.
        gt_joints: (F, J, 3) ground-truth joints in the same normalised frame.
        min_intensity: the alpha threshold (DESIGN §9: 0.2).
        nodes: "per_frame" or "fixed".

    Returns:
        SC in [0, 1]; 1 when every joint always has the same nearest keypoint.
    """
    counts, frames = _counts_jit(
        jnp.asarray(keypoints), jnp.asarray(gt_joints), min_intensity, nodes
    )
    return sc_score_from_counts(counts, float(frames))


_counts_jit = jax.jit(nearest_keypoint_counts, static_argnums=(2, 3))


class SemanticConsistency:
    """Eq. 21 over many batches: `update(kp, gt)` per batch, then `result()` (published
    definition) or `result("fixed")` (fixed node set), or `scores()` for both, named.

    The frames are kept (they are small) because the fixed node set is decided by the mean
    intensity over all of them before any nearest keypoint is counted.
    """

    def __init__(self, min_intensity: float = 0.2):
        self.min_intensity = min_intensity
        self._keypoints: list[np.ndarray] = []
        self._joints: list[np.ndarray] = []

    @property
    def frames(self) -> int:
        """Frames added so far."""
        return sum(kp.shape[0] for kp in self._keypoints)

    def update(self, keypoints: Array, gt_joints: Array) -> None:
        """Adds frames: keypoints (..., K, 4), gt_joints (..., J, 3) with equal leading axes."""
        kp = np.asarray(keypoints, np.float32)
        gt = np.asarray(gt_joints, np.float32)
        if kp.shape[:-2] != gt.shape[:-2]:
            raise ValueError(
                f"keypoints {kp.shape} and gt_joints {gt.shape} must describe the same frames "
                "(equal leading axes)"
            )
        kp, gt = kp.reshape(-1, *kp.shape[-2:]), gt.reshape(-1, *gt.shape[-2:])
        if self._keypoints and (kp.shape[1:], gt.shape[1:]) != (
            self._keypoints[0].shape[1:],
            self._joints[0].shape[1:],
        ):
            raise ValueError(
                f"SemanticConsistency: (J, K) changed from ({self._joints[0].shape[1]}, "
                f"{self._keypoints[0].shape[1]}) to ({gt.shape[1]}, {kp.shape[1]})"
            )
        self._keypoints.append(kp)
        self._joints.append(gt)

    def counts(self, nodes: str = "per_frame") -> tuple[np.ndarray, float]:
        """(J, K) nearest-keypoint counts over every frame added, and the number of frames."""
        _check_nodes(nodes)
        if not self._keypoints:
            raise ValueError("SemanticConsistency: no frame added yet; call update() first")
        counts, frames = _counts_jit(
            jnp.asarray(np.concatenate(self._keypoints)),
            jnp.asarray(np.concatenate(self._joints)),
            self.min_intensity,
            nodes,
        )
        return np.asarray(counts, np.float64), float(frames)

    def per_joint(self, nodes: str = "per_frame") -> np.ndarray:
        """(J,) max_k p_j(k) of each ground-truth joint."""
        counts, frames = self.counts(nodes)
        return counts.max(axis=-1) / frames

    def result(self, nodes: str = "per_frame") -> float:
        """Eq. 21 over every frame added so far."""
        return sc_score_from_counts(*self.counts(nodes))

    def scores(self) -> dict[str, float]:
        """Both definitions, named as every report names them: {"sc", "sc_fixed_nodes"}."""
        return {"sc": self.result("per_frame"), "sc_fixed_nodes": self.result("fixed")}


# --- bone-length variation ---------------------------------------------------------------------


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
    """Bone-length variation E_b (DESIGN §9): for every bone between kept nodes, the standard
    deviation over time of its length divided by its mean length, averaged over the bones and
    the sequences. 0 for a rigid skeleton whose bones keep their length.

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
# with ground-truth joints (DESIGN §9), ask where the kept nodes are and whether the skeleton's
# tree is the true one. Nodes and joints are matched by Euclidean distance in the normalised cube
# [-1, 1]^3. All are array math, jit- and vmap-able: the trees enter as adjacency matrices of
# their parent arrays (`tree_within`), so no graph library is needed.

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


# --- generated motion: diversity and set distance to real motion ------------------------------

# The paper shows generation only as pictures (Fig. 5); these are the measures of later skeletal
# motion-generation work, on keypoint clips (T, K, C >= 3) so that they hold at any grid size.
# Every clip-to-clip distance is the mean per-frame keypoint distance of `keypoint_distance`.


def _safe_norm(v: Array) -> Array:
    """||v|| over the last axis with a finite gradient at v = 0 (identical clips are common)."""
    sq = jnp.sum(jnp.square(v), axis=-1)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def _keypoint_weights(mask: Array | None, num_keypoints: int) -> Array:
    """(K,) weights of the mean over keypoints: 1/K each, or uniform over the `mask` ones."""
    if mask is None:
        return jnp.full((num_keypoints,), 1.0 / num_keypoints)
    mask = jnp.asarray(mask)
    if mask.shape != (num_keypoints,):
        raise ValueError(
            f"keypoint mask has shape {mask.shape} but the clips have K={num_keypoints} "
            f"keypoints; pass a ({num_keypoints},) bool mask (e.g. the pruned skeleton's nodes)"
        )
    w = mask.astype(jnp.float32)
    return w / jnp.sum(w)


def keypoint_distance(a: Array, b: Array, mask: Array | None = None) -> Array:
    """Mean per-frame keypoint distance between clips: the Euclidean distance between the xyz of
    the same keypoint in the same frame (the intensity alpha excluded), averaged over the frames
    and over the keypoints (only those of `mask` when given).

    Args:
        a, b: (..., T, K, C) clips with C >= 3 (xyz first); leading axes broadcast.
        mask: optional (K,) bool, the keypoints that count (nan when it selects none).

    Returns:
        (...) distances, in the units of the coordinates.
    """
    d = _safe_norm(a[..., :3] - b[..., :3])  # (..., T, K)
    return jnp.mean(d @ _keypoint_weights(mask, d.shape[-1]), axis=-1)


def root_relative(clips: Array, root: int) -> Array:
    """xyz relative to the root keypoint in every frame (the root translation removed):
    (..., K, C) -> (..., K, 3); the root's own row becomes 0."""
    mu = clips[..., :3]
    return mu - jnp.take(mu, jnp.asarray([root]), axis=-2)


def _check_clips(name: str, clips: Array, ndim: int, layout: str) -> None:
    if clips.ndim != ndim or clips.shape[-1] < 3:
        raise ValueError(
            f"{name}: expected {layout} keypoint clips with C >= 3 (xyz first), got shape "
            f"{clips.shape}"
        )


def clip_distances(a: Array, b: Array, mask: Array | None = None, root: int | None = None) -> Array:
    """`keypoint_distance` between every clip of `a` and every clip of `b`.

    The rows are computed one at a time (`lax.map`), so memory stays at M x T x K.

    Args:
        a: (N, T, K, C) clips; b: (M, T, K, C) clips of the same T and K.
        mask: optional (K,) bool, the keypoints that count.
        root: None compares absolute positions; a keypoint index first subtracts that keypoint's
            trajectory from every clip (`root_relative`), removing the root translation.

    Returns:
        (N, M).
    """
    _check_clips("clip_distances a", a, 4, "(N, T, K, C)")
    _check_clips("clip_distances b", b, 4, "(M, T, K, C)")
    if a.shape[1:3] != b.shape[1:3]:
        raise ValueError(
            f"clip_distances: clips of shape {a.shape} and {b.shape} differ in frames or "
            "keypoints (T, K); cut both sets to the same number of frames"
        )
    if root is not None:
        a, b = root_relative(a, root), root_relative(b, root)
    return jax.lax.map(lambda x: keypoint_distance(x[None], b, mask), a)


def diversity(samples: Array, mask: Array | None = None) -> Array:
    """Average pairwise distance (APD) of the S futures drawn for one conditioning clip: the mean
    over the S (S - 1) / 2 pairs of samples of their mean per-frame keypoint distance
    (`keypoint_distance`, absolute positions). 0 when all the samples are identical.

    Args:
        samples: (..., S, T, K, C) with S >= 2: S samples per leading index (e.g. (B, S, ...)
            for B conditioning clips); apply it to all the generated clips as one set of
            B x S samples for the spread of the set as a whole (see `set_diversity`).
        mask: optional (K,) bool, the keypoints that count.

    Returns:
        (...) one value per leading index.
    """
    if samples.ndim < 4 or samples.shape[-4] < 2 or samples.shape[-1] < 3:
        raise ValueError(
            "diversity: expected samples (..., S, T, K, C) with S >= 2 samples and C >= 3, got "
            f"shape {samples.shape}; draw at least two samples per conditioning clip"
        )
    s = samples.shape[-4]
    flat = samples.reshape(-1, *samples.shape[-4:])

    def one(x):  # (S, T, K, C) -> (); the diagonal of the distance matrix is exactly 0
        return jnp.sum(clip_distances(x, x, mask)) / (s * (s - 1))

    return jax.vmap(one)(flat).reshape(samples.shape[:-4])


def set_diversity(clips: Array, mask: Array | None = None) -> Array:
    """The spread of the generated set as a whole, split by conditioning clip.

    For every sample of conditioning clip b, the mean distance (`keypoint_distance`, absolute
    positions) to each of the B S - 1 other generated clips (its own siblings included),
    averaged over b's S samples. The mean over b equals `diversity` of all B S clips taken as
    one set; the split gives one value per conditioning clip for a confidence interval.

    Args:
        clips: (B, S, T, K, C) with B S >= 2 (S = 1 treats every clip as its own group).
        mask: optional (K,) bool, the keypoints that count.

    Returns:
        (B,).
    """
    _check_clips("set_diversity", clips, 5, "(B, S, T, K, C)")
    b, s = clips.shape[:2]
    if b * s < 2:
        raise ValueError(f"set_diversity needs at least two clips in all, got shape {clips.shape}")
    flat = clips.reshape(b * s, *clips.shape[2:])
    d = clip_distances(flat, flat, mask)  # (B S, B S), zero diagonal
    return jnp.mean((jnp.sum(d, axis=1) / (b * s - 1)).reshape(b, s), axis=1)


def nearest_clip_distances(
    generated: Array, real: Array, root: int | None, mask: Array | None = None
) -> tuple[Array, Array]:
    """The two directions of `set_distance`: for every generated clip the distance to the
    nearest real clip, and for every real clip the distance to the nearest generated clip.

    Args:
        generated: (N, T, K, C) clips; real: (M, T, K, C) clips of the same length.
        root: the skeleton's root keypoint, whose trajectory is subtracted from every clip (None
            keeps absolute positions).
        mask: optional (K,) bool, the keypoints that count.

    Returns:
        (N,) and (M,).
    """
    if generated.shape[0] == 0 or real.shape[0] == 0:
        raise ValueError(
            f"set distance of empty clip sets (generated {generated.shape}, real {real.shape}); "
            "each set needs at least one clip"
        )
    d = clip_distances(generated, real, mask, root)  # (N, M)
    return jnp.min(d, axis=1), jnp.min(d, axis=0)


def set_distance(
    generated: Array, real: Array, root: int | None, mask: Array | None = None
) -> Array:
    """Bidirectional Chamfer distance between a set of generated clips and a set of real clips.

    Every clip is one point of T x K x 3 coordinates after removing the root translation
    (`root_relative`); the distance between two clips is their mean per-frame keypoint distance
    (`keypoint_distance`, Euclidean, not squared). The result is the mean over generated clips
    of the distance to the nearest real clip (do the samples look like data?) plus the mean over
    real clips of the distance to the nearest generated clip (is the data covered?); 0 when the
    two sets are equal.

    Args:
        generated: (N, T, K, C); real: (M, T, K, C), N, M >= 1.
        root: the root keypoint (None keeps absolute positions).
        mask: optional (K,) bool, the keypoints that count.

    Returns:
        scalar.
    """
    to_real, to_generated = nearest_clip_distances(generated, real, root, mask)
    return jnp.mean(to_real) + jnp.mean(to_generated)


# --- Chamfer distances -------------------------------------------------------------------------


def _nearest_sq_dist(a: Array, b: Array, b_mask: Array, chunk: int) -> Array:
    """(N,) squared distance from each row of a (N, 3) to the nearest valid row of b (M, 3)."""
    n = a.shape[0]
    chunk = max(1, min(chunk, n))
    pad = (-n) % chunk
    blocks = jnp.pad(a, ((0, pad), (0, 0))).reshape(-1, chunk, 3)
    b_sq = jnp.sum(jnp.square(b), axis=-1)

    def block(x):  # (chunk, 3) -> (chunk,); a (chunk, M) matrix at a time, never (chunk, M, 3)
        cross = jnp.matmul(x, b.T, precision=jax.lax.Precision.HIGHEST)
        d = jnp.sum(jnp.square(x), axis=-1)[:, None] - 2.0 * cross + b_sq[None, :]
        return jnp.maximum(jnp.min(jnp.where(b_mask[None, :], d, jnp.inf), axis=-1), 0.0)

    return jax.lax.map(block, blocks).reshape(-1)[:n]


def chamfer_distance(
    a: Array,
    b: Array,
    a_mask: Array | None = None,
    b_mask: Array | None = None,
    *,
    empty_value: float = float("nan"),
    chunk: int = 2048,
) -> Array:
    """Symmetric Chamfer distance (Fan et al. 2017) between two point sets, squared distances:

    CD(A, B) = mean_{a in A} min_{b in B} ||a - b||^2 + mean_{b in B} min_{a in A} ||a - b||^2.

    Args:
        a: (N, 3) points; b: (M, 3) points.
        a_mask, b_mask: optional (N,), (M,) booleans marking the valid (non-padding) points.
        empty_value: result when exactly one set is empty (both empty gives 0).
        chunk: rows of `a` (and of `b`) compared at once; bounds memory to chunk x M floats.

    Returns:
        scalar.
    """
    a_mask = jnp.ones(a.shape[0], bool) if a_mask is None else a_mask
    b_mask = jnp.ones(b.shape[0], bool) if b_mask is None else b_mask
    na, nb = jnp.sum(a_mask), jnp.sum(b_mask)
    if a.shape[0] == 0 or b.shape[0] == 0:  # static: nothing to compare
        return jnp.asarray(0.0 if a.shape[0] == b.shape[0] else empty_value, jnp.float32)
    da = _nearest_sq_dist(a, b, b_mask, chunk)
    db = _nearest_sq_dist(b, a, a_mask, chunk)
    ab = jnp.sum(jnp.where(a_mask, da, 0.0)) / jnp.maximum(na, 1)
    ba = jnp.sum(jnp.where(b_mask, db, 0.0)) / jnp.maximum(nb, 1)
    both, neither = (na > 0) & (nb > 0), (na == 0) & (nb == 0)
    return jnp.where(both, ab + ba, jnp.where(neither, 0.0, empty_value))


@functools.partial(jax.jit, static_argnames=("empty_value",))
def _chamfer_padded(a, b, a_mask, b_mask, empty_value):
    return chamfer_distance(a, b, a_mask, b_mask, empty_value=empty_value)


def _padded(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pads (M, 3) to the next power of two (>= 64) rows with a validity mask."""
    size = max(64, 1 << int(np.ceil(np.log2(max(len(points), 1)))))
    out = np.zeros((size, 3), np.float32)
    out[: len(points)] = points
    return out, np.arange(size) < len(points)


def point_chamfer(a: np.ndarray, b: np.ndarray, empty_value: float = float("nan")) -> float:
    """`chamfer_distance` of two NumPy point sets of any size, padded to reuse compilations."""
    (pa, ma), (pb, mb) = _padded(np.asarray(a)), _padded(np.asarray(b))
    return float(_chamfer_padded(pa, pb, ma, mb, empty_value))


def _check_sequences(v: np.ndarray, v_hat: np.ndarray, name: str) -> None:
    if v.shape != v_hat.shape or v.ndim != 4:
        raise ValueError(
            f"{name}: expected two (T, G, G, G) voxel sequences of equal shape, "
            f"got {v.shape} and {v_hat.shape}"
        )


def tracking_chamfer(
    voxels: np.ndarray, recon: np.ndarray, threshold: float = 0.5, scale: float = TRACKING_SCALE
) -> float:
    """4D-tracking Chamfer distance of Table 2 (x1e4): mean over frames of CD(V_t, V-hat_t).

    V_t are the occupied cells of the ground truth, V-hat_t those of the reconstruction
    thresholded at `threshold` (cell coordinates on the linspace(-1, 1, G) grid). A frame whose
    reconstruction is empty while the ground truth is not scores the worst possible value
    (MAX_SQ_DIST = 12, the squared diagonal of the cube) instead of being skipped.

    Args:
        voxels: (T, G, G, G) ground-truth occupancy.
        recon: (T, G, G, G) reconstructed probabilities (or occupancy).
        threshold: occupancy threshold for both grids.
        scale: multiplier of the reported value (Table 2 uses 1e4).

    Returns:
        scaled mean Chamfer distance over the T frames.
    """
    voxels, recon = np.asarray(voxels), np.asarray(recon)
    _check_sequences(voxels, recon, "tracking_chamfer")
    per_frame = [
        point_chamfer(voxel_points(v, threshold), voxel_points(r, threshold), MAX_SQ_DIST)
        for v, r in zip(voxels, recon, strict=True)
    ]
    return float(np.mean(per_frame)) * scale


def motion_chamfer(voxels: np.ndarray, recon: np.ndarray, threshold: float = 0.5) -> float:
    """Motion Chamfer Distance, Eq. 22: Chamfer distances of the frame-to-frame differences.

    M-CD = 1/(T-1) sum_{t=2..T} CD(V+_t, V-hat+_t) + CD(V-_t, V-hat-_t), where V+_t (V-_t) are the
    cells that become occupied (empty) between frames t-1 and t, after thresholding both
    sequences at `threshold`. Both sets empty (no motion on either side) counts 0; exactly one
    empty counts MAX_SQ_DIST = 12 (the worst possible value), so missing motion is penalised.
    Unscaled.

    Args:
        voxels: (T, G, G, G) ground-truth sequence, T >= 2.
        recon: (T, G, G, G) generated / interpolated sequence.
        threshold: occupancy threshold.

    Returns:
        M-CD (a float).
    """
    voxels, recon = np.asarray(voxels), np.asarray(recon)
    _check_sequences(voxels, recon, "motion_chamfer")
    if voxels.shape[0] < 2:
        raise ValueError(f"motion_chamfer needs at least 2 frames, got {voxels.shape[0]}")
    occ, occ_hat = voxels >= threshold, recon >= threshold
    total = 0.0
    for t in range(1, occ.shape[0]):  # NumPy front-end: point sets differ in size per frame
        for sign in (1, -1):
            gained = occ[t] & ~occ[t - 1] if sign > 0 else occ[t - 1] & ~occ[t]
            gained_hat = occ_hat[t] & ~occ_hat[t - 1] if sign > 0 else occ_hat[t - 1] & ~occ_hat[t]
            total += point_chamfer(
                voxel_points(gained.astype(np.float32)),
                voxel_points(gained_hat.astype(np.float32)),
                MAX_SQ_DIST,
            )
    return total / (occ.shape[0] - 1)
