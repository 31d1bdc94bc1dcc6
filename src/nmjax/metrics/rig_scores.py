"""The field's scores of a discovered rig, beside SC: the tree against the true tree (tree edit
distance), the joints and bones against the true ones (CD-J2J, CD-J2B, CD-B2B) and how well the
rig reproduces its capture (the fit error).

- Tree edit distance, as the methods that discover articulation from point-cloud sequences
  report it (Reart, Liu et al. 2023: APTED; AutoURDF, 2024): `tree_edit_distance`.
- CD-J2J, CD-J2B, CD-B2B, RigNet's skeleton measures (Xu et al. 2020) as MagicArticulate (Song et
  al. 2025) re-evaluates them, both skeletons in the true body's box scaled to [-0.5, 0.5]^3 and
  reported x1e-2: `cd_j2j`, `cd_j2b`, `cd_b2b` on coordinates already in that box,
  `skeleton_chamfers` placing them there.
- The rig's fit error: the rest surface skinned by the rig against each frame's points, as a
  Chamfer distance in Table 2's units and in the capture's (`rig_fit_error`).

The tree edit distance is combinatorial (NumPy and the `apted` package); the distances are JAX
and work under `jit` and `vmap`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from nmjax.metrics.chamfer import TRACKING_SCALE, chamfer_distance

SKELETON_CD_SCALE = 1e2  # CD-J2J, CD-J2B, CD-B2B are reported x1e-2 (in hundredths of the box)
BOX_EPS = 1e-5  # added to the box's longest side, as MagicArticulate's normalisation does
BONE_SAMPLES = 64  # points per bone of CD-B2B (`cd_b2b`)


# --- tree edit distance ------------------------------------------------------------------------


# APTED's costs for unlabelled trees: delete 1, insert 1, rename 0.
UNIT_COSTS = {"del_cost": 1, "ins_cost": 1, "ren_cost": 0}


class _Node:
    """A node of the tree handed to APTED: its children, and a name all nodes share (the trees
    are unlabelled; renaming costs 0 anyway)."""

    name = ""

    def __init__(self, children: list[_Node]):
        self.children = children


def _kept_children(parents: np.ndarray, kept: np.ndarray, source: str) -> tuple[int, list]:
    """(root, children of every kept node) of the tree of the kept nodes, each kept node hanging
    off its nearest kept ancestor."""
    num = len(parents)
    index = np.arange(num)
    roots = np.flatnonzero(parents == index)
    if roots.size != 1 or np.any(parents < 0) or np.any(parents >= num):
        raise ValueError(
            f"{source}: expected parent indices 0..{num - 1} with exactly one root (its own "
            f"parent), got {parents.tolist()}"
        )
    root = int(roots[0])
    if not kept[root]:
        raise ValueError(f"{source}: the kept mask drops the root {root}; a kept tree keeps it")
    # K steps up from every node reach the root unless the node hangs off a cycle.
    up, steps = parents.copy(), 0
    while steps < num and np.any(up != root):
        up, steps = parents[up], steps + 1
    if np.any(up != root):
        raise ValueError(f"{source}: entries never reach the root {root} in {parents.tolist()}")
    children: list[list[int]] = [[] for _ in range(num)]
    for k in np.flatnonzero(kept & (index != root)):  # each kept node once, up to its ancestor
        p = int(parents[k])
        while not kept[p]:
            p = int(parents[p])
        children[p].append(int(k))
    return root, children


def _canonical_tree(parents, kept, source: str) -> _Node:
    """The kept tree with every node's children sorted by the shape of their subtrees (the
    AHU canonical string: a leaf is "()", a node "(" + its children's strings, sorted, + ")"), so
    that the ordered tree depends only on the unordered one, not on how its nodes are numbered."""
    parents = np.asarray(parents)
    if parents.ndim != 1 or parents.size == 0 or not np.issubdtype(parents.dtype, np.integer):
        raise ValueError(f"{source}: expected a non-empty (K,) integer parent array")
    parents = parents.astype(np.int64)
    kept = np.ones(len(parents), bool) if kept is None else np.asarray(kept, bool)
    if kept.shape != parents.shape:
        raise ValueError(f"{source}: kept mask {kept.shape} does not match parents {parents.shape}")
    root, children = _kept_children(parents, kept, source)
    order, frontier = [], [root]
    while frontier:  # breadth first; built back to front, children before their parent
        order += frontier
        frontier = [c for k in frontier for c in children[k]]
    shape: dict[int, str] = {}
    node: dict[int, _Node] = {}
    for k in reversed(order):
        ranked = sorted(children[k], key=lambda c: shape[c])
        shape[k] = "(" + "".join(shape[c] for c in ranked) + ")"
        node[k] = _Node([node[c] for c in ranked])
    return node[root]


def tree_edit_distance(parents_a, parents_b, kept_a=None, kept_b=None) -> int:
    """Tree edit distance between two rooted, unlabelled trees (Zhang & Shasha 1989), computed
    by APTED (Pawlik & Augsten 2015, the `apted` package), as Reart and AutoURDF score a
    discovered kinematic tree against the true one.

    The least number of edits turning tree A into tree B, with unit costs: deleting a node (its
    children take its place under its parent) costs 1, inserting one costs 1, and renaming costs
    0 because the nodes carry no labels (nothing says which discovered node is which true
    joint). Moving a leaf to another parent therefore costs 2 (one delete, one insert), or 0
    when the result has the same shape; trees of N_A and N_B nodes are between |N_A - N_B|
    (every extra node is deleted or inserted) and N_A + N_B - 2 (all but the roots deleted and
    inserted, the roots mapped onto each other for free) apart.

    APTED computes the edit distance of ordered trees; the unordered one is NP-hard. The children
    of every node are put in a canonical order (sorted by the shape of their subtrees) so that
    the value depends only on the shapes, never on the node numbering: an upper bound on the
    unordered distance (0 exactly when the two trees have the same shape).

    Args:
      parents_a, parents_b: (K_a,), (K_b,) parent index of every node; the root is its own
        parent (nmjax's convention, `nmjax.parents`).
      kept_a, kept_b: optional (K,) bool masks: only the kept nodes form the tree, each hanging
        off its nearest kept ancestor (a run's pruned skeleton, `skeleton.prune`); the root
        must be kept. None keeps every node.

    Returns:
      the distance, an integer >= 0.

    Raises:
      ValueError: a parent array that is not a tree, or a mask of another length or without the
        root.
    """
    # Imported where it is used: nothing else of nmjax needs the package, and the GPU image the
    # paper-scale runs use has no way to install it (experiments/gpu/fetch_wheels.sh).
    from apted import APTED, PerEditOperationConfig

    tree_a = _canonical_tree(parents_a, kept_a, "tree_edit_distance: tree A")
    tree_b = _canonical_tree(parents_b, kept_b, "tree_edit_distance: tree B")
    costs = PerEditOperationConfig(**UNIT_COSTS)
    return int(APTED(tree_a, tree_b, costs).compute_edit_distance())


# --- CD-J2J, CD-J2B, CD-B2B --------------------------------------------------------------------


def _norm(x: Array) -> Array:
    """Euclidean norm over the last axis, with gradient 0 (not NaN) at the zero vector."""
    sq = jnp.sum(jnp.square(x), axis=-1)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def _mask(mask: Array | None, count: int) -> Array:
    return jnp.ones(count, bool) if mask is None else jnp.asarray(mask, bool)


def _mean_nearest(
    dist: Array, a_valid: Array, b_valid: Array, a_weight: Array | None = None
) -> Array:
    """(..., A, B) distances -> (...,): the mean over the valid rows (weighted by `a_weight`)
    of each row's smallest distance to a valid column; NaN without a valid row or column."""
    nearest = jnp.min(jnp.where(b_valid[..., None, :], dist, jnp.inf), axis=-1)
    weight = jnp.broadcast_to(a_valid, nearest.shape).astype(dist.dtype)
    if a_weight is not None:
        weight = weight * a_weight
    total = jnp.sum(weight, axis=-1)
    found = jnp.sum(jnp.where(weight > 0, nearest * weight, 0.0), axis=-1)
    ok = (total > 0) & jnp.any(b_valid, axis=-1)
    return jnp.where(ok, found / jnp.where(ok, total, 1.0), jnp.nan)


def _bones(joints: Array, parents, mask: Array) -> tuple[Array, Array, Array]:
    """(parent ends (..., K, 3), child ends (..., K, 3), valid (K,)) of every joint's bone to its
    parent; a bone is valid when both ends are kept and the joint is not the root."""
    parents = np.asarray(parents, np.int64).reshape(-1)
    if parents.shape != (joints.shape[-2],):
        raise ValueError(
            f"parents {parents.shape} do not match the {joints.shape[-2]} joints of {joints.shape}"
        )
    valid = mask & mask[parents] & jnp.asarray(parents != np.arange(len(parents)))
    return joints[..., parents, :], joints, valid


def _segment_distances(points: Array, start: Array, end: Array) -> Array:
    """(..., P, 3) points, (..., B, 3) segment ends -> (..., P, B) distance from every point to
    the nearest point of every segment (a zero-length segment is its one point)."""
    d = end - start
    sq = jnp.sum(jnp.square(d), axis=-1)[..., None, :]  # (..., 1, B)
    rel = points[..., :, None, :] - start[..., None, :, :]  # (..., P, B, 3)
    t = jnp.sum(rel * d[..., None, :, :], axis=-1) / jnp.where(sq > 0, sq, 1.0)
    t = jnp.where(sq > 0, jnp.clip(t, 0.0, 1.0), 0.0)
    return _norm(rel - t[..., None] * d[..., None, :, :])


def _check_joints(joints: Array, name: str) -> Array:
    joints = jnp.asarray(joints)
    if joints.ndim < 2 or joints.shape[-1] != 3:
        raise ValueError(f"{name}: joints must have shape (..., J, 3), got {joints.shape}")
    return joints


def cd_j2j(joints_a: Array, joints_b: Array, mask_a=None, mask_b=None) -> Array:
    """CD-J2J (RigNet, Xu et al. 2020; MagicArticulate's evaluation): the symmetric mean
    nearest-joint distance, Euclidean (not squared),

        CD-J2J = 1/2 (mean_{a in A} min_{b in B} ||a - b|| + mean_{b in B} min_{a in A} ||a - b||).

    Args:
      joints_a: (..., A, 3), joints_b: (..., B, 3) joint positions, in any common units (the
        box of `skeleton_chamfers` for the reported value).
      mask_a, mask_b: optional (A,), (B,) bool: the joints that count (e.g. a run's kept nodes).

    Returns:
      (...,) in the units of the input; NaN where a side has no joint.
    """
    a, b = _check_joints(joints_a, "cd_j2j"), _check_joints(joints_b, "cd_j2j")
    ma, mb = _mask(mask_a, a.shape[-2]), _mask(mask_b, b.shape[-2])
    dist = _norm(a[..., :, None, :] - b[..., None, :, :])  # (..., A, B)
    there = _mean_nearest(dist, ma, mb)
    back = _mean_nearest(jnp.swapaxes(dist, -1, -2), mb, ma)
    return 0.5 * (there + back)


def cd_j2b(
    joints_a: Array, parents_a, joints_b: Array, parents_b, mask_a=None, mask_b=None
) -> Array:
    """CD-J2B (RigNet; MagicArticulate's evaluation): every joint's distance to the nearest bone
    of the other skeleton, averaged over the joints, symmetric:

        CD-J2B = 1/2 (mean_{a in A} min_{bone of B} d(a, bone) + mean_{b in B} min_{bone of A} d).

    d is the exact distance from a point to a line segment. MagicArticulate's released code
    samples every bone at steps of 0.005 of the box and takes the nearest sample; the exact
    segment distance is that value's limit and differs from it by less than half a step.

    Args:
      joints_a: (..., A, 3), joints_b: (..., B, 3) joint positions.
      parents_a, parents_b: (A,), (B,) parent of every joint, the root its own (NumPy, static);
        a bone joins a joint to its parent.
      mask_a, mask_b: optional (A,), (B,) bool kept joints: a masked joint is no joint and ends
        no bone (give the pruned tree, whose kept nodes hang off kept nodes).

    Returns:
      (...,) in the units of the input; NaN where a side has no joint or no bone.
    """
    a, b = _check_joints(joints_a, "cd_j2b"), _check_joints(joints_b, "cd_j2b")
    ma, mb = _mask(mask_a, a.shape[-2]), _mask(mask_b, b.shape[-2])
    sa, ea, va = _bones(a, parents_a, ma)
    sb, eb, vb = _bones(b, parents_b, mb)
    there = _mean_nearest(_segment_distances(a, sb, eb), ma, vb)
    back = _mean_nearest(_segment_distances(b, sa, ea), mb, va)
    return 0.5 * (there + back)


def _bone_samples(start: Array, end: Array, valid: Array, samples: int):
    """(..., B * S, 3) points at the midpoints of S equal pieces of every bone, their weights
    (..., B * S) (the bone's length / S: every unit of bone length counts alike, or 1 each when
    the whole skeleton has length 0) and validity (B * S,)."""
    t = (jnp.arange(samples, dtype=start.dtype) + 0.5) / samples
    points = start[..., :, None, :] + t[:, None] * (end - start)[..., :, None, :]
    length = jnp.where(valid, _norm(end - start), 0.0)  # (..., B)
    weight = jnp.repeat(length / samples, samples, axis=-1)
    flat_valid = jnp.repeat(valid, samples)
    has_length = jnp.sum(weight, axis=-1, keepdims=True) > 0
    weight = jnp.where(has_length, weight, flat_valid.astype(weight.dtype))
    return points.reshape(*points.shape[:-3], -1, 3), weight, flat_valid


def cd_b2b(
    joints_a: Array,
    parents_a,
    joints_b: Array,
    parents_b,
    mask_a=None,
    mask_b=None,
    samples: int = BONE_SAMPLES,
) -> Array:
    """CD-B2B (RigNet; MagicArticulate's evaluation): the distance between the two skeletons'
    bones, sampled along the bones, symmetric:

        CD-B2B = 1/2 (mean_{x on A's bones} min_{bone of B} d(x, bone) + the same from B to A),

    the mean taken along the bones by length. Fixed here where the papers leave it open: each
    bone is sampled at the midpoints of `samples` = 64 equal pieces, each sample weighted by the
    bone's length / 64 (so every unit of bone length counts alike, as MagicArticulate's samples
    every 0.005 of the box do; a bone up to 0.32 long, a third of the box, is sampled at least
    that densely), and a sample's distance to the other skeleton is the exact distance to its
    nearest bone segment (the limit of MagicArticulate's nearest sample). A skeleton whose bones
    all have length 0 counts each of its samples alike.

    Args:
      joints_a: (..., A, 3), joints_b: (..., B, 3); parents_a, parents_b: (A,), (B,) (static);
      mask_a, mask_b: optional kept joints (see `cd_j2b`).
      samples: points per bone.

    Returns:
      (...,) in the units of the input; NaN where a side has no bone.
    """
    a, b = _check_joints(joints_a, "cd_b2b"), _check_joints(joints_b, "cd_b2b")
    ma, mb = _mask(mask_a, a.shape[-2]), _mask(mask_b, b.shape[-2])
    sa, ea, va = _bones(a, parents_a, ma)
    sb, eb, vb = _bones(b, parents_b, mb)
    pa, wa, fa = _bone_samples(sa, ea, va, samples)
    pb, wb, fb = _bone_samples(sb, eb, vb, samples)
    there = _mean_nearest(_segment_distances(pa, sb, eb), fa, vb, wa)
    back = _mean_nearest(_segment_distances(pb, sa, ea), fb, va, wb)
    return 0.5 * (there + back)


def unit_box(points: Array, body: Array) -> Array:
    """`points` placed in the bounding box of `body`, centred and scaled by its longest side
    (+1e-5) so that the body spans [-0.5, 0.5] along it: MagicArticulate's normalisation of a
    mesh and its skeleton before CD-J2J / J2B / B2B.

    Args:
      points: (..., M, 3); body: (..., N, 3) the true body (its points or mesh vertices), with
        the same leading axes (e.g. one box per frame).

    Returns:
      (..., M, 3).
    """
    lo, hi = jnp.min(body, axis=-2, keepdims=True), jnp.max(body, axis=-2, keepdims=True)
    side = jnp.max(hi - lo, axis=-1, keepdims=True) + BOX_EPS
    return (points - 0.5 * (lo + hi)) / side


def skeleton_chamfers(
    joints: Array,
    parents,
    true_joints: Array,
    true_parents,
    body: Array,
    kept=None,
    samples: int = BONE_SAMPLES,
) -> dict[str, Array]:
    """CD-J2J, CD-J2B and CD-B2B of a skeleton against the true one, as reported: both skeletons
    in the true body's box scaled to [-0.5, 0.5]^3 (`unit_box`), x1e-2 (`SKELETON_CD_SCALE`).

    Args:
      joints: (..., K, 3) the skeleton's joints (a run's keypoints, xyz); parents: (K,) its
        tree (the pruned one with `kept`).
      true_joints: (..., J, 3); true_parents: (J,) the true tree, or None (then only CD-J2J).
      body: (..., N, 3) the true body the box is taken from, one per leading index (a frame).
      kept: optional (K,) bool kept nodes.
      samples: points per bone of CD-B2B.

    Returns:
      {"cd_j2j", "cd_j2b", "cd_b2b"} each (...,), the last two only with `true_parents`.
    """
    x, y = unit_box(joints, body), unit_box(true_joints, body)
    out = {"cd_j2j": cd_j2j(x, y, kept)}
    if true_parents is not None:
        out["cd_j2b"] = cd_j2b(x, parents, y, true_parents, kept)
        out["cd_b2b"] = cd_b2b(x, parents, y, true_parents, kept, samples=samples)
    return {key: value * SKELETON_CD_SCALE for key, value in out.items()}


# --- the rig's fit error -----------------------------------------------------------------------


@jax.jit
def _frame_chamfers(skinned: Array, frames: Array) -> Array:
    return jax.vmap(functools.partial(chamfer_distance, empty_value=float("nan")))(skinned, frames)


def rig_fit_error(skinned: Array, frames: Array, box_scale: float) -> dict[str, float]:
    """The rig's fit error: its skinned surface against the capture, frame by frame.

    `skinned` is the capture's frame-0 surface (its points or mesh vertices) skinned with the
    rig's weights and driven by the rig's motion (linear blend skinning of each joint's world
    rotation and position relative to the rest pose, `nmjax.tasks.retarget_vertices`); the
    error is the symmetric Chamfer distance of squared distances (`chamfer_distance`, Table 2's
    definition) between it and each frame's points, averaged over the frames. 0 when the rig
    reproduces the capture.

    Args:
      skinned: (T, V, 3) the skinned surface in the normalised cube of the crop.
      frames: (T, N, 3) the capture's points in the same cube.
      box_scale: the normalisation's factor s of p' = s (p - bmin) - 1
        (`nmjax.data.normalize.normalization_box`), which maps the capture into the cube.

    Returns:
      {"cd": the mean x1e4 in the cube (Table 2's units, as the tracking CD),
       "cd_capture": the same mean in the capture's units, squared (cube / s^2)}.
    """
    skinned, frames = jnp.asarray(skinned, jnp.float32), jnp.asarray(frames, jnp.float32)
    if skinned.ndim != 3 or frames.ndim != 3 or skinned.shape[0] != frames.shape[0]:
        raise ValueError(
            f"rig_fit_error: skinned (T, V, 3) and frames (T, N, 3) must have the same T, got "
            f"{skinned.shape} and {frames.shape}"
        )
    if not box_scale > 0:
        raise ValueError(f"rig_fit_error: box_scale must be > 0, got {box_scale}")
    mean = float(jnp.mean(_frame_chamfers(skinned, frames)))
    return {"cd": mean * TRACKING_SCALE, "cd_capture": mean / float(box_scale) ** 2}
