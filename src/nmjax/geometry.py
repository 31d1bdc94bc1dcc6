"""Rotations, forward kinematics and linear blend skinning (paper Eqs. 1-2, 24-25, appendix A.4;
docs/architecture.md §8-9): the one home of each in nmjax.

Rotation matrices act on column vectors (`R @ d`); their columns are the rotated x, y, z axes.
Quaternions are (w, x, y, z). Every JAX function is pure and works under `jit`, `vmap` and `grad`
with finite gradients, including at degenerate inputs (zero vectors, identical rotations).

The functions ending in `_np` are NumPy twins for the NumPy data generators (the synthetic bodies
of `nmjax.data.synthetic`, SMPL / MANO in `nmjax.data.body_models`), which pose thousands of
frames in float64 outside any trace; each computes what its JAX function computes (tested on
random inputs against it).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np
from jax import Array

_EPS = 1e-8


def _safe_norm(x: Array, axis: int = -1, keepdims: bool = False) -> Array:
    """Euclidean norm with gradient 0 (not NaN) at the zero vector."""
    sq = jnp.sum(jnp.square(x), axis=axis, keepdims=keepdims)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def normalize(x: Array, axis: int = -1, eps: float = _EPS) -> Array:
    """x / max(||x||, eps) along `axis`."""
    return x / jnp.maximum(_safe_norm(x, axis=axis, keepdims=True), eps)


# --- representations ---------------------------------------------------------------------------


# The release's 6D conversion divides by ||v|| + 1e-10 (not max(||v||, eps)).
RELEASE_6D_EPS = 1e-10


def rotation_6d_to_matrix(d6: Array) -> Array:
    """6D rotation representation (Zhou et al. 2019) -> rotation matrix, as the release computes
    it: x = a1 / (||a1|| + 1e-10), z = (x cross a2) / (||x cross a2|| + 1e-10), y = z cross x.

    These are the matrix's columns. For any input whose halves are not parallel and not tiny
    this is Gram-Schmidt (x, then a2's part orthogonal to x): orthonormal with determinant +1;
    at a near-zero half the additive epsilon shrinks the axes instead of clamping the norm
    (a1 = (1e-9, 0, 0), a2 = (0, 1, 0) gives diag(1/1.1, 1/1.1, 1)).

    Args:
        d6: (..., 6).

    Returns:
        (..., 3, 3) rotation matrices, columns (x, y, z).
    """
    a1, a2 = d6[..., :3], d6[..., 3:]
    x = a1 / (_safe_norm(a1, keepdims=True) + RELEASE_6D_EPS)
    z = jnp.cross(x, a2)
    z = z / (_safe_norm(z, keepdims=True) + RELEASE_6D_EPS)
    y = jnp.cross(z, x)
    return jnp.stack([x, y, z], axis=-1)


def matrix_to_rotation_6d(rot: Array) -> Array:
    """Rotation matrix -> 6D representation: the first two columns, concatenated.

    Args:
        rot: (..., 3, 3).

    Returns:
        (..., 6); `rotation_6d_to_matrix` inverts it for rotation matrices.
    """
    return jnp.concatenate([rot[..., :, 0], rot[..., :, 1]], axis=-1)


def _skew(w: Any, xp: Any) -> Any:
    """(..., 3) -> (..., 3, 3) cross-product matrices [w], [w] d = w x d; `xp` is jnp or np."""
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    zero = xp.zeros_like(x)
    rows = [zero, -z, y, z, zero, -x, -y, x, zero]
    return xp.stack(rows, axis=-1).reshape(*w.shape[:-1], 3, 3)


def axis_angle_to_matrix(axis_angle: Array) -> Array:
    """Rodrigues' formula: rotation by |w| radians about w / |w|.

    Args:
        axis_angle: (..., 3) rotation vectors.

    Returns:
        (..., 3, 3); the identity for a zero vector (with a finite gradient there).
    """
    theta = _safe_norm(axis_angle)[..., None, None]
    small = theta < 1e-6
    safe_theta = jnp.where(small, 1.0, theta)
    skew = _skew(axis_angle, jnp)
    # sin(t)/t and (1 - cos(t))/t^2 with their Taylor series near 0.
    a = jnp.where(small, 1.0 - theta**2 / 6, jnp.sin(safe_theta) / safe_theta)
    b = jnp.where(small, 0.5 - theta**2 / 24, (1.0 - jnp.cos(safe_theta)) / safe_theta**2)
    eye = jnp.eye(3, dtype=axis_angle.dtype)
    return eye + a * skew + b * (skew @ skew)


def quaternion_to_matrix(quat: Array) -> Array:
    """Unit quaternion (w, x, y, z) -> rotation matrix (the input is normalised first).

    Args:
        quat: (..., 4).

    Returns:
        (..., 3, 3).
    """
    w, x, y, z = jnp.moveaxis(normalize(quat), -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def matrix_to_quaternion(rot: Array) -> Array:
    """Rotation matrix -> unit quaternion (w, x, y, z) with w >= 0.

    Shepperd's method: of the four candidate formulas, the one with the largest denominator is
    used, so the result is accurate for every rotation (also near 180 degrees).

    Args:
        rot: (..., 3, 3) rotation matrices.

    Returns:
        (..., 4).
    """
    m = rot
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # 4 q_i^2 for i = w, x, y, z.
    four_sq = jnp.stack(
        [
            1 + m00 + m11 + m22,
            1 + m00 - m11 - m22,
            1 - m00 + m11 - m22,
            1 - m00 - m11 + m22,
        ],
        axis=-1,
    )
    d21, d02, d10 = (
        m[..., 2, 1] - m[..., 1, 2],
        m[..., 0, 2] - m[..., 2, 0],
        m[..., 1, 0] - m[..., 0, 1],
    )
    s21, s02, s10 = (
        m[..., 2, 1] + m[..., 1, 2],
        m[..., 0, 2] + m[..., 2, 0],
        m[..., 1, 0] + m[..., 0, 1],
    )
    # Row i: 4 q_i * (w, x, y, z).
    candidates = jnp.stack(
        [
            jnp.stack([four_sq[..., 0], d21, d02, d10], axis=-1),
            jnp.stack([d21, four_sq[..., 1], s10, s02], axis=-1),
            jnp.stack([d02, s10, four_sq[..., 2], s21], axis=-1),
            jnp.stack([d10, s02, s21, four_sq[..., 3]], axis=-1),
        ],
        axis=-2,
    )
    best = jnp.argmax(four_sq, axis=-1)
    chosen = jnp.take_along_axis(candidates, best[..., None, None], axis=-2)[..., 0, :]
    quat = normalize(chosen)
    return quat * jnp.where(quat[..., :1] < 0, -1.0, 1.0)


def align_rotation(u: Array, v: Array) -> Array:
    """The smallest rotation taking unit vectors u to v: (..., 3), (..., 3) -> (..., 3, 3).

    Rodrigues' formula about u x v; antiparallel inputs turn by pi about an axis normal to u.
    """
    u, v = normalize(u), normalize(v)
    c = jnp.sum(u * v, axis=-1)[..., None, None]
    axis = jnp.cross(u, v)
    # For u = -v any axis normal to u works: u x e_x, or u x e_y when u is along x.
    fallback = jnp.cross(u, jnp.where(jnp.abs(u[..., :1]) < 0.9, jnp.eye(3)[0], jnp.eye(3)[1]))
    anti = (c[..., 0, 0] < -1.0 + 1e-6)[..., None]
    axis = jnp.where(anti, normalize(fallback), axis)
    skew = _skew(axis, jnp)
    eye = jnp.eye(3)
    general = eye + skew + skew @ skew / (1.0 + jnp.where(anti[..., None], 0.0, c))
    flip = 2.0 * axis[..., :, None] * axis[..., None, :] - eye  # rotation by pi about `axis`
    return jnp.where(anti[..., None], flip, general)


# --- interpolation -----------------------------------------------------------------------------


def slerp(q0: Array, q1: Array, t: Array | float) -> Array:
    """Spherical linear interpolation of unit quaternions along the shorter arc.

    slerp(t) = sin((1 - t) theta) / sin(theta) q0 + sin(t theta) / sin(theta) q1', where q1' is
    q1 or -q1 (whichever is closer to q0) and cos(theta) = <q0, q1'>; nearly identical inputs fall
    back to normalised linear interpolation.

    Args:
        q0, q1: (..., 4) unit quaternions (w, x, y, z).
        t: interpolation parameter, broadcastable to (...); 0 gives q0, 1 gives q1 (up to sign).

    Returns:
        (..., 4) unit quaternions.
    """
    t = jnp.asarray(t, dtype=q0.dtype)[..., None]
    dot = jnp.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = jnp.where(dot < 0, -q1, q1)
    dot = jnp.abs(dot)
    near = dot > 1.0 - 1e-6
    theta = jnp.arccos(jnp.where(near, 0.0, jnp.clip(dot, -1.0, 1.0)))
    sin_theta = jnp.where(near, 1.0, jnp.sin(theta))
    w0 = jnp.where(near, 1.0 - t, jnp.sin((1.0 - t) * theta) / sin_theta)
    w1 = jnp.where(near, t, jnp.sin(t * theta) / sin_theta)
    return normalize(w0 * q0 + w1 * q1)


def slerp_matrices(r0: Array, r1: Array, t: Array | float) -> Array:
    """Slerp between rotation matrices (through quaternions), e.g. local joint rotations.

    Args:
        r0, r1: (..., 3, 3) rotation matrices.
        t: broadcastable to (...).

    Returns:
        (..., 3, 3): r0 at t = 0, r1 at t = 1, the constant-speed geodesic in between.
    """
    return quaternion_to_matrix(slerp(matrix_to_quaternion(r0), matrix_to_quaternion(r1), t))


def _matmul(a: Array, b: Array) -> Array:
    """(..., 3, 3) @ (..., 3, 3) as a broadcast multiply-and-sum (see forward kinematics)."""
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


# --- forward kinematics (Eq. 2) ----------------------------------------------------------------


def tree_levels(parents: Sequence[int] | np.ndarray, order: Sequence[int] | np.ndarray) -> list:
    """Groups joints by depth below the root (NumPy, at trace time).

    Args:
        parents: (K,) parent index per joint; the root is its own parent.
        order: (K,) topological order, root first.

    Returns:
        list of int arrays: [root], its children, their children, ... (tree depth + 1 levels).
    """
    parents = np.asarray(parents, dtype=np.int64).reshape(-1)
    order = np.asarray(order, dtype=np.int64).reshape(-1)
    k = parents.shape[0]
    if order.shape[0] != k or sorted(order.tolist()) != list(range(k)):
        raise ValueError(f"order must be a permutation of 0..{k - 1}, got {order.tolist()}")
    if np.any(parents < 0) or np.any(parents >= k):
        raise ValueError(f"parents must index 0..{k - 1}, got {parents.tolist()}")
    root = int(order[0])
    if parents[root] != root:
        raise ValueError(f"order[0]={root} must be the root (its own parent), parents={parents}")
    depth = np.full(k, -1, dtype=np.int64)
    depth[root] = 0
    for j in order[1:]:
        if j == parents[j] or depth[parents[j]] < 0:
            raise ValueError(
                f"order {order.tolist()} is not topological for parents {parents.tolist()}: "
                f"joint {j} comes before its parent {parents[j]} or is a second root"
            )
        depth[j] = depth[parents[j]] + 1
    return [np.flatnonzero(depth == d) for d in range(int(depth.max()) + 1)]


def _checked_tree(
    parents: Sequence[int] | np.ndarray, order: Sequence[int] | np.ndarray, root_pos, rots, offsets
) -> tuple[list, np.ndarray, tuple[int, ...]]:
    """(`tree_levels`, parents as a (K,) int array, the broadcast batch shape) of an FK call,
    after checking its arrays' shapes."""
    levels = tree_levels(parents, order)
    parents = np.asarray(parents, dtype=np.int64).reshape(-1)
    k = parents.shape[0]
    if rots.shape[-3:] != (k, 3, 3):
        raise ValueError(f"local_rots must be (..., {k}, 3, 3) for {k} joints, got {rots.shape}")
    if offsets.shape[-2:] != (k, 3):
        raise ValueError(f"offsets must be (K, 3) or (..., K, 3) with K={k}, got {offsets.shape}")
    lead = np.broadcast_shapes(root_pos.shape[:-1], rots.shape[:-3], offsets.shape[:-2])
    return levels, parents, lead


def forward_kinematics_with_rotations(
    root_pos: Array,
    local_rots: Array,
    offsets: Array,
    parents: Sequence[int] | np.ndarray,
    order: Sequence[int] | np.ndarray,
) -> tuple[Array, Array]:
    """Eq. 2: joint positions and global rotations from local rotations along a skeleton tree.

    R_root = R~_root, mu_root = root_pos; for every other joint k (parents first)
    R_k = R_parent(k) R~_k and mu_k = mu_parent(k) + R_k d_k. As printed in Eq. 2 (and Eq. 24),
    a joint's offset is rotated by its own global rotation, which includes its local rotation.

    Vectorised: the joints of one tree depth are updated together, so the trace has one gather /
    3x3 product per level (tree depth), never a loop over joints; it compiles, with its
    gradient, for any number of batch axes and under `vmap`. `parents` and `order` are static
    (Python / NumPy integers, e.g. from `Skeleton`).

    Args:
        root_pos: (..., 3) root position.
        local_rots: (..., K, 3, 3) rotation of each joint relative to its parent.
        offsets: (K, 3) or (..., K, 3) rest-pose offset d_k from the parent (Eq. 1); the root's
            is ignored.
        parents: (K,) parent indices, the root its own parent.
        order: (K,) topological order, root first.

    Returns:
        positions (..., K, 3) and global rotations (..., K, 3, 3).
    """
    levels, parents, lead = _checked_tree(parents, order, root_pos, local_rots, offsets)
    k = parents.shape[0]
    local_rots = jnp.broadcast_to(local_rots, (*lead, k, 3, 3))
    offsets = jnp.broadcast_to(offsets, (*lead, k, 3))
    root = int(levels[0][0])
    # One array per depth level; a joint's parent sits in the previous level, found by a static
    # index into it. The levels are concatenated and put back in joint order at the end: static
    # gathers only, no scatters. The 3x3 products are written as broadcast multiply-and-sum:
    # XLA:CPU (jax 0.10.2) crashes in its algebraic simplifier on the gradient of a batched
    # dot_general of gathered operands when there are several batch axes or a vmap.
    glob_levels = [local_rots[..., root : root + 1, :, :]]
    pos_levels = [jnp.broadcast_to(root_pos, (*lead, 3))[..., None, :]]
    for prev, level in zip(levels[:-1], levels[1:], strict=True):  # tree depth, not joints
        slot = {int(j): i for i, j in enumerate(prev)}
        par = np.array([slot[int(parents[j])] for j in level])
        r = _matmul(glob_levels[-1][..., par, :, :], local_rots[..., level, :, :])
        step = jnp.sum(r * offsets[..., level, None, :], axis=-1)  # R_k d_k
        glob_levels.append(r)
        pos_levels.append(pos_levels[-1][..., par, :] + step)
    back = np.argsort(np.concatenate(levels))  # level order -> joint order
    glob = jnp.concatenate(glob_levels, axis=-3)[..., back, :, :]
    pos = jnp.concatenate(pos_levels, axis=-2)[..., back, :]
    return pos, glob


def forward_kinematics(
    root_pos: Array,
    local_rots: Array,
    offsets: Array,
    parents: Sequence[int] | np.ndarray,
    order: Sequence[int] | np.ndarray,
) -> Array:
    """Eq. 2: joint positions (..., K, 3); see `forward_kinematics_with_rotations`."""
    return forward_kinematics_with_rotations(root_pos, local_rots, offsets, parents, order)[0]


def bone_offsets(
    positions: Array, parents: Sequence[int] | np.ndarray, directions: Array | None = None
) -> Array:
    """Eq. 1 / Eq. 25: offsets d_k = mu_k - mu_parent(k), or unit `directions` x bone length.

    Args:
        positions: (..., K, 3) joint positions of one pose.
        parents: (K,) parent indices (root its own parent, so its offset is 0).
        directions: optional (K, 3) or (..., K, 3) directions d-bar_k; normalised here.

    Returns:
        (..., K, 3).
    """
    par = np.asarray(parents, dtype=np.int64).reshape(-1)
    d = positions - positions[..., par, :]
    if directions is None:
        return d
    return normalize(directions) * _safe_norm(d, keepdims=True)


# --- linear blend skinning (appendix A.4) ------------------------------------------------------


def linear_blend_skinning(
    vertices: Any,
    weights: Any,
    transforms: Any = None,
    *,
    rotations: Any = None,
    translations: Any = None,
) -> Array:
    """Linear blend skinning v' = sum_k w_vk (R_k v + t_k) (appendix A.4).

    Give either `transforms` (..., K, 4, 4) homogeneous joint transforms, or `rotations`
    (..., K, 3, 3) and `translations` (..., K, 3). Works under jit / vmap / grad.

    Args:
      vertices: (V, 3) rest-pose vertices.
      weights: (V, K) skin weights.

    Returns:
      (..., V, 3) deformed vertices.
    """
    if (transforms is None) == (rotations is None and translations is None):
        raise ValueError("give either transforms or both rotations and translations")
    if transforms is not None:
        transforms = jnp.asarray(transforms)
        rotations, translations = transforms[..., :3, :3], transforms[..., :3, 3]
    elif rotations is None or translations is None:
        raise ValueError("rotations and translations must be given together")
    v = jnp.asarray(vertices)
    w = jnp.asarray(weights)
    rotations, translations = jnp.asarray(rotations), jnp.asarray(translations)
    if v.ndim != 2 or v.shape[-1] != 3 or w.shape != (v.shape[0], rotations.shape[-3]):
        raise ValueError(
            f"vertices (V, 3) and weights (V, K) must match the K={rotations.shape[-3]} "
            f"transforms; got {v.shape} and {w.shape}"
        )
    per_joint = jnp.einsum("...kij,vj->...kvi", rotations, v) + translations[..., :, None, :]
    return jnp.einsum("vk,...kvi->...vi", w, per_joint)


# --- NumPy twins (see the module docstring) ----------------------------------------------------


def axis_angle_to_matrix_np(axis_angle: Any, angle: Any = None) -> np.ndarray:
    """NumPy twin of `axis_angle_to_matrix`: Rodrigues' formula R = I + sin(t) [k] + (1 - cos(t))
    [k]^2 for the unit axis k and angle t, in float64.

    Used by `nmjax.data.body_models` (SMPL / MANO poses, rotation vectors) and
    `nmjax.data.synthetic` (a body's joint rotations, a fixed axis and an angle per frame).

    Args:
      axis_angle: (..., 3) rotation vectors (the angle in radians times the unit axis); or, when
        `angle` is given, axes of any non-zero length (normalised here).
      angle: None, or (...) angles in radians, broadcastable against `axis_angle`'s (...).

    Returns:
      (..., 3, 3); the identity for a zero rotation vector.
    """
    axis = np.asarray(axis_angle, dtype=np.float64)
    length = np.linalg.norm(axis, axis=-1)
    angle = length if angle is None else np.asarray(angle, dtype=np.float64)
    k = axis / np.where(length > 0, length, 1.0)[..., None]  # a zero vector: no axis, R = I
    cross = _skew(k, np)
    s, c = np.sin(angle)[..., None, None], np.cos(angle)[..., None, None]
    return np.eye(3) + s * cross + (1.0 - c) * (cross @ cross)


def align_rotation_np(u: Any, v: Any) -> np.ndarray:
    """NumPy twin of `align_rotation`, float64: the smallest rotation turning direction u onto
    direction v, (..., 3) x2 -> (..., 3, 3); a zero vector on either side gives the identity.

    Used by `nmjax.export.rig` (the swing rotations of a motion known by its positions).
    """
    u, v = np.asarray(u, np.float64), np.asarray(v, np.float64)
    nu, nv = np.linalg.norm(u, axis=-1), np.linalg.norm(v, axis=-1)
    degenerate = (nu < 1e-12) | (nv < 1e-12)
    u = u / np.where(degenerate, 1.0, nu)[..., None]
    v = v / np.where(degenerate, 1.0, nv)[..., None]
    c = np.sum(u * v, axis=-1)
    skew = _skew(np.cross(u, v), np)
    eye = np.broadcast_to(np.eye(3), (*c.shape, 3, 3))
    opposite = c < -1.0 + 1e-9  # float64 resolves the general formula closer to -1 than float32
    general = eye + skew + skew @ skew / np.where(opposite, 1.0, 1.0 + c)[..., None, None]
    # Any axis normal to u turns it onto -u: u x e_x, or u x e_y when u lies along x.
    other = np.where(np.abs(u[..., :1]) < 0.9, np.eye(3)[0], np.eye(3)[1])
    normal = np.cross(u, other)
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    flip = 2.0 * normal[..., :, None] * normal[..., None, :] - eye  # pi about `normal`
    out = np.where(opposite[..., None, None], flip, general)
    return np.where(degenerate[..., None, None], eye, out)


def forward_kinematics_np(
    root_pos: Any,
    local_rots: Any,
    offsets: Any,
    parents: Sequence[int] | np.ndarray,
    order: Sequence[int] | np.ndarray,
    *,
    offset_frame: str = "own",
) -> tuple[np.ndarray, np.ndarray]:
    """NumPy twin of `forward_kinematics_with_rotations`: positions and global rotations, float64.

    R_root = R~_root, mu_root = root_pos, R_k = R_parent(k) R~_k for every other joint; the
    offset d_k is rotated by the joint's own global rotation (`offset_frame="own"`, Eq. 2 as
    printed: mu_k = mu_parent(k) + R_k d_k) or by its parent's (`offset_frame="parent"`: mu_k =
    mu_parent(k) + R_parent(k) d_k, the convention of SMPL's kinematic chain and of the synthetic
    bodies, whose offsets place a joint on its parent's frame). The two agree when every d_k of
    "parent" is R~_k times that of "own".

    Used by `nmjax.data.body_models` (SMPL / MANO's chain) and `nmjax.data.synthetic` (posing a
    body). One vectorised step per tree depth, as the JAX function.

    Args:
      root_pos: (..., 3).
      local_rots: (..., K, 3, 3) rotations relative to the parent.
      offsets: (K, 3) or (..., K, 3) (they may change per frame, e.g. a sliding joint); the
        root's is ignored.
      parents: (K,) parent indices, the root its own parent.
      order: (K,) topological order, root first.
      offset_frame: "own" or "parent" (above).

    Returns:
      positions (..., K, 3) and global rotations (..., K, 3, 3).
    """
    if offset_frame not in ("own", "parent"):
        raise ValueError(f"offset_frame must be 'own' or 'parent', got {offset_frame!r}")
    root_pos = np.asarray(root_pos, dtype=np.float64)
    local_rots = np.asarray(local_rots, dtype=np.float64)
    offsets = np.asarray(offsets, dtype=np.float64)
    levels, parents, lead = _checked_tree(parents, order, root_pos, local_rots, offsets)
    k = parents.shape[0]
    local_rots = np.broadcast_to(local_rots, (*lead, k, 3, 3))
    offsets = np.broadcast_to(offsets, (*lead, k, 3))
    positions, rotations = np.empty((*lead, k, 3)), np.empty((*lead, k, 3, 3))
    root = int(levels[0][0])
    positions[..., root, :] = root_pos
    rotations[..., root, :, :] = local_rots[..., root, :, :]
    for level in levels[1:]:  # tree depth, not joints
        par = parents[level]
        glob = rotations[..., par, :, :] @ local_rots[..., level, :, :]
        frame = glob if offset_frame == "own" else rotations[..., par, :, :]
        step = np.einsum("...ij,...j->...i", frame, offsets[..., level, :])
        positions[..., level, :] = positions[..., par, :] + step
        rotations[..., level, :, :] = glob
    return positions, rotations


def linear_blend_skinning_np(
    vertices: Any, weights: Any, rotations: Any, translations: Any
) -> np.ndarray:
    """NumPy twin of `linear_blend_skinning` (its rotations / translations form), float64:
    v' = sum_k w_vk (R_k v + t_k).

    Used by `nmjax.data.body_models` (skinning SMPL / MANO meshes, whose rest vertices change per
    frame with the pose blend shapes). The joints' [R | t] are blended per vertex first, one
    (V, K) @ (..., K, 12) product, so the cost does not grow with V x K per frame.

    Args:
      vertices: (V, 3) or (..., V, 3) rest-pose vertices.
      weights: (V, K) skin weights.
      rotations: (..., K, 3, 3).
      translations: (..., K, 3).

    Returns:
      (..., V, 3) deformed vertices.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    rotations = np.asarray(rotations, dtype=np.float64)
    weights = np.asarray(weights)
    if (
        vertices.ndim < 2
        or vertices.shape[-1] != 3
        or weights.shape
        != (
            vertices.shape[-2],
            rotations.shape[-3],
        )
    ):
        raise ValueError(
            f"vertices (..., V, 3) and weights (V, K) must match the K={rotations.shape[-3]} "
            f"rotations; got {vertices.shape} and {weights.shape}"
        )
    per_joint = np.concatenate([rotations, np.asarray(translations)[..., None]], axis=-1)
    blended = weights @ per_joint.reshape(*per_joint.shape[:-2], 12)
    blended = blended.reshape(*blended.shape[:-1], 3, 4)
    return (blended[..., :3] @ vertices[..., None])[..., 0] + blended[..., 3]
