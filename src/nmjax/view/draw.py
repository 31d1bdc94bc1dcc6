"""What a view draws, as plain functions of arrays: colours and sizes of keypoints, bone and
affinity pairs, cylinder poses, the scene's axes. No viser here."""

from __future__ import annotations

import colorsys
from collections.abc import Iterable

import numpy as np

GREY = (160, 160, 160)  # pruned keypoints
BONE_COLOR = (40, 40, 40)
GENERATED_BONE_COLOR = (230, 110, 20)  # bones of frames the model generated
ROOT_COLOR = (20, 20, 20)  # a wire ball around the root keypoint
TRUTH_COLOR = (30, 150, 60)
REFINED_COLOR = (200, 40, 160)  # the skeleton `nmjax refine` fitted
BODY_COLOR = (120, 160, 210)
AFFINITY_COLOR = (50, 50, 190)
MESH_COLOR = (200, 180, 150)

KEYPOINT_RADIUS = 0.035  # in the normalised cube [-1, 1)^3
POINT_SIZE = 0.012
PANEL_SPACING = 2.6  # between the centres of side-by-side motions (each fills a 2-wide cube)
MIN_SIZE = 0.3  # radius of an alpha = 0 keypoint, as a fraction of an alpha = 1 one


def keypoint_colors(num: int, keep: np.ndarray | None = None) -> np.ndarray:
    """(K, 3) uint8 colours by keypoint index, GREY where `keep` (K,) is False.

    Hues step by the golden ratio, so neighbouring indices get far-apart colours.
    """
    hues = (np.arange(num) * 0.618033988749895) % 1.0
    colors = np.array([colorsys.hsv_to_rgb(h, 0.8, 0.92) for h in hues]) * 255.0
    colors = np.round(colors).astype(np.uint8).reshape(num, 3)
    if keep is not None:
        colors[~np.asarray(keep, bool)] = GREY
    return colors


def keypoint_radii(alpha: np.ndarray, radius: float = KEYPOINT_RADIUS) -> np.ndarray:
    """(K,) sphere radii growing linearly with intensity: alpha (K,) in [0, 1] -> radius *
    [MIN_SIZE, 1], so a keypoint that fades out stays visible."""
    return radius * (MIN_SIZE + (1.0 - MIN_SIZE) * np.clip(alpha, 0.0, 1.0))


def bone_pairs(parents: Iterable[int], keep: np.ndarray | None = None) -> np.ndarray:
    """(B, 2) (parent, child) index pairs of a tree, the root's self-link and every child
    outside `keep` (K,) left out. With the parents of `skeleton.prune`, every bone then links two
    kept nodes."""
    parents = np.asarray(list(parents), np.int64)
    keep = np.ones(len(parents), bool) if keep is None else np.asarray(keep, bool)
    children = np.flatnonzero((parents != np.arange(len(parents))) & keep)
    return np.stack([parents[children], children], axis=1).reshape(-1, 2)


def affinity_pairs(influence: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every keypoint pair k < k' and its link strength for drawing the learned affinity.

    Args:
      influence: (K, K) I = max_n A_n (`skeleton.influence`).

    Returns:
      pairs (P, 2), P = K (K - 1) / 2, and strengths (P,) = max(I[k, k'], I[k', k]) divided by
      the largest of them (all zero when the affinity is).
    """
    influence = np.asarray(influence, np.float64)
    first, second = np.triu_indices(len(influence), k=1)
    strength = np.maximum(influence[first, second], influence[second, first])
    top = strength.max(initial=0.0)
    return np.stack([first, second], axis=1), (strength / top if top > 0 else strength)


def cylinder_transforms(
    starts: np.ndarray, ends: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Poses of unit cylinders (axis z, height 1, centred) stretched from `starts` to `ends`.

    Args:
      starts, ends: (P, 3) segment end points.

    Returns:
      centres (P, 3), orientations (P, 4) as quaternions (w, x, y, z) turning +z onto the
      segment direction (half-way quaternion; a segment along -z turns about x), lengths (P,).
    """
    delta = np.asarray(ends, np.float64) - np.asarray(starts, np.float64)
    lengths = np.linalg.norm(delta, axis=-1)
    d = delta / np.maximum(lengths, 1e-12)[:, None]
    d[lengths < 1e-12] = (0.0, 0.0, 1.0)
    # q = (1 + z.d, z x d) normalised is the rotation by the angle between z and d.
    q = np.stack([1.0 + d[:, 2], -d[:, 1], d[:, 0], np.zeros(len(d))], axis=1)
    flip = q[:, 0] < 1e-9
    q[flip] = (0.0, 1.0, 0.0, 0.0)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return (np.asarray(starts) + np.asarray(ends)) / 2.0, q, lengths


def view_axes(up_axis: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(up, towards the viewer, rightwards) unit vectors of a scene whose up axis is `up_axis`.

    Side-by-side motions are laid out rightwards and their rows downwards; the camera looks
    against `towards` (for z up: from -y, x to the right).
    """
    eye = np.eye(3)
    up, towards = eye[up_axis], -eye[(up_axis + 2) % 3]
    return up, towards, np.cross(up, towards)


def clamp_frame(t: int, length: int) -> int:
    """Frame `t` of a motion of `length` frames; a shorter motion holds its last frame."""
    return int(min(max(t, 0), length - 1))


def unit_cylinder():
    """A trimesh cylinder of radius 1 and height 1 along z, centred at the origin."""
    import trimesh

    return trimesh.creation.cylinder(radius=1.0, height=1.0, sections=8)
