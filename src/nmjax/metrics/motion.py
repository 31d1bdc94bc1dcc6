"""Measures of generated motion on keypoint clips: diversity (of one input's samples and of the
generated set) and the set distance to real motion.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array

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
