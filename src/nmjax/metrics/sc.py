"""SC-score, Eq. 21 (paper Table 1): how consistently every ground-truth joint keeps the same
nearest keypoint (docs/architecture.md §9).

`nearest_keypoint_counts` is the pure, jit-able kernel; `SemanticConsistency` accumulates its
counts over many batches.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

# How the candidates for "nearest keypoint" are chosen (docs/architecture.md §9):
# "per_frame": the published SC-score: in every frame, the keypoints whose alpha in that frame is
#   >= the threshold. The default; what `nmjax evaluate` reports as "sc".
# "fixed": one node set over all the frames, the keypoints whose mean alpha is >= the threshold
#   (the pruned skeleton's nodes); reported beside it as "sc_fixed_nodes".
SC_NODES = ("per_frame", "fixed")


def skeleton_nodes(keypoints: Array, min_intensity: float = 0.2) -> Array:
    """The keypoints that are nodes of the pruned skeleton: mean intensity >= `min_intensity`.

    The intensity is averaged over all the given frames, so the node set is one fixed set, as
    the pruned skeleton of docs/architecture.md §7 (alpha < 0.2 removed); the brightest keypoint
    always stays.

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
        min_intensity: the alpha threshold (docs/architecture.md §9: 0.2).
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
        min_intensity: the alpha threshold (docs/architecture.md §9: 0.2).
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
