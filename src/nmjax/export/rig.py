"""The rig an export writes: a skeleton, its motion and an optional skinned mesh (pure NumPy).

Conventions (shared by the glTF and BVH writers, `nmjax.export`):

- A motion is given as world transforms: joint positions mu (T, J, 3) and world rotations R
  (T, J, 3, 3), plus a rest (bind) pose of the same two kinds. nmjax's forward kinematics
  (Eq. 2) rotates the bone from parent p to joint k by k's own rotation, mu_k = mu_p + R_k d_k,
  while a glTF node or a BVH joint rotates the bones *below* it. So that every joint lands
  exactly where nmjax puts it (siblings turn independently in nmjax, which one parent
  rotation cannot reproduce), each joint of the file carries nmjax's rotation R_k as its world
  rotation and its position as a translation in its parent's frame, R_p^T (mu_k - mu_p), whose
  length is the bone's (`local_transforms`).
- A motion known only as positions (phase-1 keypoints, a generated or interpolated motion) gets
  rotations from its bones (`swing_rotations`): each joint turns by the smallest rotation that
  takes its rest bone onto its bone at frame t. Two points do not define a twist about the
  bone, so the twist stays at rest; the root, which has no bone, keeps its rest orientation.
- The file's axes: glTF is +Y up with the front facing +Z; BVH files are read the same way by
  the common tools. `file_axes` turns the data's axes (up axis 0/1/2) into those, keeping the
  side `nmjax view` shows the body from as the front.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from nmjax import geometry

EULER_ORDER = "ZXY"  # BVH rotation channels: Zrotation Xrotation Yrotation, R = Rz Rx Ry
MAX_INFLUENCES = 4  # glTF's JOINTS_0 / WEIGHTS_0 hold four joints per vertex


@dataclasses.dataclass(frozen=True)
class Rig:
    """A skeleton with its motion and an optional skinned mesh, everything in world coordinates.

    Attributes:
      name: what the motion is (a sequence, a sample), for the file's animation name.
      joints: (J,) keypoint index of every joint (written as `joint_<k>`), parents first.
      parents: (J,) parent of every joint as an index into `joints`; joint 0 is the root, its
        own parent.
      positions: (T, J, 3) joint positions.
      rotations: (T, J, 3, 3) joint world rotations.
      rest_positions: (J, 3), rest_rotations: (J, 3, 3): the rest (bind) pose.
      frame_rate: frames per second.
      vertices: (V, 3) mesh in the rest pose, or None (a skeleton only).
      faces: (F, 3) triangles of the mesh, or None: the vertices are a point cloud (written as
        glTF POINTS).
      weights: (V, J) skin weights, rows summing to 1.
    """

    name: str
    joints: np.ndarray
    parents: np.ndarray
    positions: np.ndarray
    rotations: np.ndarray
    rest_positions: np.ndarray
    rest_rotations: np.ndarray
    frame_rate: float
    vertices: np.ndarray | None = None
    faces: np.ndarray | None = None
    weights: np.ndarray | None = None

    @property
    def num_frames(self) -> int:
        return int(self.positions.shape[0])

    @property
    def names(self) -> list[str]:
        return [f"joint_{k}" for k in self.joints]

    def children(self, j: int) -> list[int]:
        """The joints whose parent is joint j, in joint order."""
        return [c for c in range(1, len(self.parents)) if self.parents[c] == j]


def kept_tree(
    parents: np.ndarray, order: np.ndarray, keep: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The kept keypoints as a tree of their own: each hangs off its nearest kept ancestor.

    Args:
      parents: (K,) parent of every keypoint, the root its own.
      order: (K,) topological order, root first.
      keep: (K,) bool; the root is kept whatever it says.

    Returns:
      joints (J,) the kept keypoints in `order` and parents (J,) as indices into `joints`.
    """
    parents, keep = np.asarray(parents), np.array(keep, bool)
    root = int(order[0])
    keep[root] = True
    ancestor = parents.copy()
    for k in order[1:]:  # parents first, so ancestor[p] is already a kept node
        p = parents[k]
        ancestor[k] = p if keep[p] else ancestor[p]
    joints = np.array([k for k in order if keep[k]], np.int64)
    index = {int(k): i for i, k in enumerate(joints)}
    return joints, np.array([index[int(ancestor[k])] for k in joints], np.int64)


def swing_rotations(
    positions: np.ndarray, rest_positions: np.ndarray, parents: np.ndarray
) -> np.ndarray:
    """World rotations of a motion known by its joint positions: swing only.

    Joint k turns by the smallest rotation taking its rest bone (mu_k - mu_p at rest) onto its
    bone at frame t; the twist about the bone stays at rest (two points do not define it) and
    the root keeps the identity.

    Args:
      positions: (T, J, 3); rest_positions: (J, 3); parents: (J,) root first.

    Returns:
      (T, J, 3, 3) rotations relative to a rest pose whose rotations are the identity.
    """
    parents = np.asarray(parents)
    rest_bones = rest_positions - rest_positions[parents]  # (J, 3), the root's is zero
    bones = positions - positions[:, parents]  # (T, J, 3)
    return geometry.align_rotation_np(np.broadcast_to(rest_bones, bones.shape), bones)


def local_transforms(
    positions: np.ndarray, rotations: np.ndarray, parents: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Each joint's transform in its parent's frame (a glTF node's TRS, a BVH joint's channels).

    Root: rotation R_root, translation mu_root. Joint k with parent p: rotation R_p^T R_k and
    translation R_p^T (mu_k - mu_p), so composing them down the tree (`compose`) gives back
    (mu, R) exactly.

    Args:
      positions: (..., J, 3) world positions; rotations: (..., J, 3, 3) world rotations.
      parents: (J,) root first (its own parent).

    Returns:
      local rotations (..., J, 3, 3) and local translations (..., J, 3).
    """
    parents = np.asarray(parents)
    parent_rot = rotations[..., parents, :, :]
    local_rot = np.swapaxes(parent_rot, -1, -2) @ rotations
    offset = positions - positions[..., parents, :]
    local_trans = np.einsum("...kji,...kj->...ki", parent_rot, offset)
    local_rot[..., 0, :, :] = rotations[..., 0, :, :]
    local_trans[..., 0, :] = positions[..., 0, :]
    return local_rot, local_trans


def compose(
    local_rot: np.ndarray, local_trans: np.ndarray, parents: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Forward kinematics by glTF's (and BVH's) rule: world = parent's world x local.

    Args:
      local_rot: (..., J, 3, 3); local_trans: (..., J, 3); parents: (J,) parents first.

    Returns:
      world positions (..., J, 3) and rotations (..., J, 3, 3).
    """
    rot, pos = np.array(local_rot, np.float64), np.array(local_trans, np.float64)
    for j in range(1, len(parents)):
        p = parents[j]
        pos[..., j, :] = pos[..., p, :] + np.einsum(
            "...ij,...j->...i", rot[..., p, :, :], pos[..., j, :]
        )
        rot[..., j, :, :] = rot[..., p, :, :] @ rot[..., j, :, :]
    return pos, rot


def file_axes(up_axis: int) -> np.ndarray:
    """(3, 3) rotation from data axes with up axis `up_axis` to the file's (+Y up, +Z front).

    Rows: the data's rightwards, up and towards-the-viewer directions, which become +X, +Y and
    +Z; the same directions as `nmjax view` lays its scenes out in (`nmjax.view.view_axes`,
    which imports this module's readers, so the three lines are repeated here).
    """
    eye = np.eye(3)
    up, towards = eye[up_axis], -eye[(up_axis + 2) % 3]
    return np.stack([np.cross(up, towards), up, towards])


def transform(rig: Rig, axes: np.ndarray) -> Rig:
    """The rig with every position turned by the rotation `axes` (3, 3) and every rotation
    conjugated by it (R -> A R A^T), so local transforms are those of the turned body."""

    def turn(x: np.ndarray | None) -> np.ndarray | None:
        return None if x is None else x @ axes.T

    def conj(r: np.ndarray) -> np.ndarray:
        return axes @ r @ np.swapaxes(axes, -1, -2)

    return dataclasses.replace(
        rig,
        positions=turn(rig.positions),
        rotations=conj(rig.rotations),
        rest_positions=turn(rig.rest_positions),
        rest_rotations=conj(rig.rest_rotations),
        vertices=turn(rig.vertices),
    )


def inverse_bind_matrices(rest_positions: np.ndarray, rest_rotations: np.ndarray) -> np.ndarray:
    """(J, 4, 4) inverses of the joints' rest world transforms [R | mu]: [R^T | -R^T mu]."""
    out = np.zeros((len(rest_positions), 4, 4))
    rt = np.swapaxes(rest_rotations, -1, -2)
    out[:, :3, :3] = rt
    out[:, :3, 3] = -np.einsum("kij,kj->ki", rt, rest_positions)
    out[:, 3, 3] = 1.0
    return out


def top_influences(
    weights: np.ndarray, count: int = MAX_INFLUENCES
) -> tuple[np.ndarray, np.ndarray]:
    """The `count` largest skin weights of every vertex, renormalised to sum to 1.

    Algorithm 2 gives a vertex at most two non-zero weights (the two ends of its bone), so for
    nmjax's weights nothing is dropped and the skinning is exact.

    Args:
      weights: (V, J) non-negative, every row with a positive sum.

    Returns:
      joint indices (V, count) int and weights (V, count) float32 summing to 1 in float32.

    Raises:
      ValueError: a vertex without weight, or negative weights.
    """
    weights = np.asarray(weights, np.float64)
    if np.any(weights < 0) or np.any(weights.sum(axis=1) <= 0):
        raise ValueError("skin weights must be non-negative with every vertex weighted")
    padded = np.pad(weights, ((0, 0), (0, max(count - weights.shape[1], 0))))
    index = np.argsort(-padded, axis=1, kind="stable")[:, :count]
    top = np.take_along_axis(padded, index, axis=1)
    top /= top.sum(axis=1, keepdims=True)
    top = top.astype(np.float32)
    # The largest weight takes up the float32 rounding, so every row sums to 1 in float32.
    top[:, 0] = np.float32(1.0) - top[:, 1:].sum(axis=1, dtype=np.float32)
    index = np.where(top > 0, index, 0)  # padding slots point at joint 0 with weight 0
    return index, top


def euler_zxy(rotations: np.ndarray) -> np.ndarray:
    """Euler angles in degrees (z, x, y) with R = Rz(z) Rx(x) Ry(y) (`EULER_ORDER`).

    BVH's "Zrotation Xrotation Yrotation": intrinsic rotations about z, then the new x, then
    the new y. At x = +-90 degrees (gimbal lock) y is set to 0.

    Args:
      rotations: (..., 3, 3).

    Returns:
      (..., 3) degrees, x in [-90, 90].
    """
    r = np.asarray(rotations, np.float64)
    cos_x = np.hypot(r[..., 0, 1], r[..., 1, 1])
    x = np.arctan2(r[..., 2, 1], cos_x)
    locked = cos_x < 1e-9
    z = np.where(
        locked, np.arctan2(r[..., 1, 0], r[..., 0, 0]), np.arctan2(-r[..., 0, 1], r[..., 1, 1])
    )
    y = np.where(locked, 0.0, np.arctan2(-r[..., 2, 0], r[..., 2, 2]))
    return np.degrees(np.stack([z, x, y], axis=-1))


def matrix_from_euler_zxy(angles: np.ndarray) -> np.ndarray:
    """Rz(z) Rx(x) Ry(y) of angles (..., 3) in degrees (z, x, y): the inverse of `euler_zxy`."""
    z, x, y = np.moveaxis(np.radians(np.asarray(angles, np.float64)), -1, 0)
    one, zero = np.ones_like(z), np.zeros_like(z)

    def matrix(*rows):
        return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)

    rz = matrix([np.cos(z), -np.sin(z), zero], [np.sin(z), np.cos(z), zero], [zero, zero, one])
    rx = matrix([one, zero, zero], [zero, np.cos(x), -np.sin(x)], [zero, np.sin(x), np.cos(x)])
    ry = matrix([np.cos(y), zero, np.sin(y)], [zero, one, zero], [-np.sin(y), zero, np.cos(y)])
    return rz @ rx @ ry


def quaternions_xyzw(rotations: np.ndarray) -> np.ndarray:
    """(T, J, 3, 3) rotations -> (T, J, 4) unit quaternions (x, y, z, w), glTF's order, with
    each joint's sign chosen along time so consecutive keys are on the same hemisphere (glTF
    interpolates linearly between the stored values)."""
    from scipy.spatial.transform import Rotation

    shape = rotations.shape[:-2]
    quat = Rotation.from_matrix(rotations.reshape(-1, 3, 3)).as_quat().reshape(*shape, 4)
    for t in range(1, shape[0]):
        flip = np.sum(quat[t] * quat[t - 1], axis=-1) < 0
        quat[t, flip] *= -1.0
    return quat
