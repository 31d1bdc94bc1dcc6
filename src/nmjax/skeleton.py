"""Skeleton extraction (paper Sec. 4, appendix A.3, Algorithm 1) and skinning (A.4, Algorithm 2).

Runs between the phases on the learned affinity, in NumPy/SciPy: the result is a kinematic tree
over all K keypoints (`Skeleton`), written as `skeleton.json` into the phase-1 run folder. The
skinning half (`skin_weights`, `linear_blend_skinning`) deforms a target mesh with joint
transforms for retargeting.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np
from scipy.sparse import csgraph

from nmjax import io

NO_PATH = 1e4  # Algorithm 1: hop distance written for "no path" between two keypoints
PRUNE_THRESHOLD = 0.2  # keypoints with mean intensity alpha below this are pruned (paper figures)
DEFAULT_NEIGHBORS = 2  # N of Algorithm 1: maximum neighbours each keypoint links to


@dataclasses.dataclass(frozen=True)
class Skeleton:
    """A rooted kinematic tree over K keypoints.

    Attributes:
      parents: (K,) parent of every keypoint; the root is its own parent.
      root: index of the root keypoint.
      order: (K,) topological order (breadth first, children by index), root first.
      depth: number of edges on the longest root-to-leaf path.
    """

    parents: tuple[int, ...]
    root: int
    order: tuple[int, ...]
    depth: int

    @property
    def num_keypoints(self) -> int:
        return len(self.parents)

    def edges(self) -> list[tuple[int, int]]:
        """(parent, child) pairs in topological order."""
        return [(self.parents[k], k) for k in self.order if k != self.root]

    def to_json(self) -> dict[str, Any]:
        return {
            "parents": list(self.parents),
            "root": self.root,
            "order": list(self.order),
            "depth": self.depth,
        }

    def save(self, path: str | os.PathLike, **extras: Any) -> None:
        """Writes the tree plus `extras` (arrays become nested lists) as JSON, atomically."""
        payload = self.to_json()
        for key, value in extras.items():
            payload[key] = np.asarray(value).tolist() if isinstance(value, np.ndarray) else value
        io.write_json(path, payload)


def skeleton_from_parents(parents: Any) -> Skeleton:
    """Builds a `Skeleton` from a parent array, checking that it is a single rooted tree.

    Args:
      parents: (K,) ints; exactly one entry is its own parent (the root).

    Raises:
      ValueError: indices out of range, not exactly one root, or a cycle.
    """
    parents = np.asarray(parents)
    if parents.ndim != 1 or parents.size == 0 or not np.issubdtype(parents.dtype, np.integer):
        raise ValueError(f"parents must be a non-empty 1-D integer array, got {parents!r}")
    num = parents.size
    if parents.min() < 0 or parents.max() >= num:
        raise ValueError(f"parents {parents.tolist()} index keypoints outside 0..{num - 1}")
    roots = np.flatnonzero(parents == np.arange(num))
    if roots.size != 1:
        raise ValueError(
            f"parents {parents.tolist()} must have exactly one root (own parent), found "
            f"{roots.tolist()}"
        )
    root = int(roots[0])
    children: list[list[int]] = [[] for _ in range(num)]
    for k in range(num):
        if k != root:
            children[int(parents[k])].append(k)
    order, depths = [root], {root: 0}
    for k in order:  # breadth first; the list grows while it is walked
        for c in children[k]:
            depths[c] = depths[k] + 1
            order.append(c)
    if len(order) != num:
        cyclic = sorted(set(range(num)) - set(order))
        raise ValueError(f"parents {parents.tolist()} contain a cycle through {cyclic}")
    return Skeleton(
        parents=tuple(int(p) for p in parents),
        root=root,
        order=tuple(order),
        depth=max(depths.values()),
    )


def load_skeleton(path: str | os.PathLike) -> Skeleton:
    """Reads a `skeleton.json` written by `Skeleton.save` and validates it.

    Raises:
      FileNotFoundError: no such file (extract it with `nmjax extract-skeleton --run RUN`).
      ValueError: the file lacks `parents` or they do not form a tree.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} not found; write it with `nmjax extract-skeleton --run <phase-1 run>`"
        )
    data = json.loads(path.read_text())
    if "parents" not in data:
        raise ValueError(f"{path} has no 'parents' field; re-run `nmjax extract-skeleton`")
    try:
        skeleton = skeleton_from_parents(np.asarray(data["parents"], dtype=np.int64))
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from e
    if "root" in data and int(data["root"]) != skeleton.root:
        raise ValueError(f"{path}: root {data['root']} is not the parents' root {skeleton.root}")
    return skeleton


def influence(affinity: Any) -> np.ndarray:
    """Influence max_n A_n of the N learned affinities (DESIGN section 7).

    Args:
      affinity: (K, K) or (N, K, K) non-negative affinities; row i is keypoint i's preference.

    Returns:
      (K, K) float64 with a zero diagonal.

    Raises:
      ValueError: wrong shape, non-finite or negative entries.
    """
    a = np.asarray(affinity, dtype=np.float64)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3 or a.shape[1] != a.shape[2] or a.shape[1] == 0:
        raise ValueError(f"affinity must have shape (K, K) or (N, K, K), got {a.shape}")
    if not np.all(np.isfinite(a)) or np.any(a < 0):
        raise ValueError("affinity must be finite and non-negative (softmaxed affinities)")
    a = a.max(axis=0)
    np.fill_diagonal(a, 0.0)
    return a


def binarize_affinity(a: np.ndarray, n_neighbors: int) -> np.ndarray:
    """BinarizeAffinity of Algorithm 1 (line 1): symmetric neighbourhood matrix A^bin.

    Keypoint i links to at most `n_neighbors` keypoints: its strongest ones (ties by index) among
    those whose affinity exceeds the mean of row i's off-diagonal entries (for softmaxed rows the
    uniform level 1/(K-1)), so a leaf whose row puts all mass on one neighbour gets no spurious
    second edge. The links are then symmetrised (an edge if either end chose it), which lets a
    keypoint have more than N neighbours (a palm with five fingers).

    Args:
      a: (K, K) influence with a zero diagonal.
      n_neighbors: N >= 1.

    Returns:
      (K, K) bool, symmetric, zero diagonal.
    """
    num = a.shape[0]
    bin_ = np.zeros((num, num), dtype=bool)
    if num == 1:
        return bin_
    row_mean = a.sum(axis=1, keepdims=True) / (num - 1)
    # Stable argsort of -a: strongest first, equal values by lower index.
    ranked = np.argsort(-a, axis=1, kind="stable")[:, : min(n_neighbors, num - 1)]
    rows = np.arange(num)[:, None]
    chosen = a[rows, ranked] > row_mean
    bin_[np.broadcast_to(rows, ranked.shape)[chosen], ranked[chosen]] = True
    np.fill_diagonal(bin_, False)
    return bin_ | bin_.T


def hop_distances(bin_: np.ndarray) -> np.ndarray:
    """Dijkstra on the unweighted graph A^bin (Algorithm 1 line 2); NO_PATH where unreachable."""
    dist = csgraph.dijkstra(bin_.astype(np.float64), directed=False, unweighted=True)
    return np.where(np.isfinite(dist), dist, NO_PATH)


def _argmin_sum(dist: np.ndarray, candidates: np.ndarray) -> int:
    """The candidate with the smallest summed distance to all keypoints, ties by index."""
    sums = dist[candidates].sum(axis=1)
    return int(candidates[np.argmin(sums)])


def connect_components(bin_: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Lines 2-10 of Algorithm 1: root, then join components root-to-pseudo-root until one.

    The pseudo root of the other components is the keypoint outside the root's component with
    the smallest summed hop distance (unreachable counts NO_PATH, so the largest remaining
    component is joined first, at its most central keypoint).

    Returns:
      (A^bin connected, hop distances (K, K), root).
    """
    bin_ = bin_.copy()
    num = bin_.shape[0]
    everyone = np.arange(num)
    dist = hop_distances(bin_)
    root = _argmin_sum(dist, everyone)
    while True:
        _, labels = csgraph.connected_components(bin_, directed=False)
        outside = np.flatnonzero(labels != labels[root])
        if outside.size == 0:
            return bin_, dist, root
        k = _argmin_sum(dist, outside)
        bin_[root, k] = bin_[k, root] = True
        dist = hop_distances(bin_)
        root = _argmin_sum(dist, everyone)


def refine_graph(
    a: np.ndarray, bin_: np.ndarray, hops: np.ndarray, root: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RefineGraph of Algorithm 1 (line 12): affinity-weighted distances and ranks.

    Every A^bin edge (i, j) gets length 1 - log(s_ij / max s), s_ij = max(A_ij, A_ji) the
    symmetrised influence (clipped at 1e-6 of the largest), so a hop along a strong edge costs
    about 1 and a hop along a weak one (e.g. an edge added to join components) costs more.
    Nodes are then ranked by (hop level from the root, refined distance to the root, index):
    rank 0 is the root, and keypoints on the same hop level are the "same rank" of lines 21-31.

    Returns:
      refined: (K,) refined distance to the root.
      level: (K,) int hop level (distance to the root in A^bin).
      rank: (K,) int position of each keypoint in that order (a permutation of 0..K-1).
    """
    s = np.maximum(a, a.T)
    s = s / s.max() if s.max() > 0 else np.ones_like(s)
    length = 1.0 - np.log(np.clip(s, 1e-6, 1.0))
    refined = csgraph.dijkstra(np.where(bin_, length, 0.0), directed=False, indices=root)
    level = hops[root].astype(np.int64)
    order = np.lexsort((np.arange(len(level)), refined, level))
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return refined, level, rank


def find_parents(
    a: np.ndarray, bin_: np.ndarray, level: np.ndarray, rank: np.ndarray
) -> np.ndarray:
    """Lines 14-33 of Algorithm 1: parent of every keypoint, processed in rank order.

    H(i) are i's neighbours on a lower hop level (non-empty for every non-root node because
    levels are breadth-first distances in a connected graph). The normal parent is the member of
    H(i) closest in rank to i (the youngest ancestor). For same-level neighbours j of i that are
    ranked before i, taken in rank order, let l be the highest-ranked (closest to the root)
    member of H(i) & H(j); if l prefers j (A_lj > A_li), j becomes i's parent. A parent always has
    a strictly smaller rank, so following parents reaches the root and the result is a tree.

    Returns:
      (K,) int parents; the root is its own parent.
    """
    num = len(rank)
    parents = np.arange(num)
    for i in np.argsort(rank)[1:]:
        neighbours = np.flatnonzero(bin_[i])
        higher = neighbours[level[neighbours] < level[i]]
        parents[i] = higher[np.argmax(rank[higher])]
        same = neighbours[(level[neighbours] == level[i]) & (rank[neighbours] < rank[i])]
        for j in same[np.argsort(rank[same])]:
            nj = np.flatnonzero(bin_[j])
            shared = np.intersect1d(higher, nj[level[nj] < level[j]])
            if shared.size == 0:
                continue
            l_ = shared[np.argmin(rank[shared])]
            if a[l_, j] > a[l_, i]:
                parents[i] = j
                break
    return parents


def extract_skeleton(
    affinity: Any, n_neighbors: int = DEFAULT_NEIGHBORS, intensities: Any = None
) -> Skeleton:
    """Algorithm 1: the kinematic tree over all K keypoints from the learned affinity.

    Steps: influence max_n A_n; `binarize_affinity` (top-N neighbours above the row mean,
    symmetrised); `connect_components` (hop distances by Dijkstra, root = argmin of summed
    distances, root-to-pseudo-root edges until connected); `refine_graph` (affinity-weighted
    Dijkstra, ranks); `find_parents` (youngest higher-rank neighbour, same-rank rule).
    Deterministic: every tie goes to the lower keypoint index.

    Args:
      affinity: (K, K) or (N, K, K) non-negative affinity (contract C10 `affinity.npy`).
      n_neighbors: N, the maximum number of neighbours each keypoint links to.
      intensities: optional (K,) mean keypoint intensities; only checked here (they drive
        `prune` and the skin weights, not the topology).

    Returns:
      A `Skeleton` over all K keypoints.

    Raises:
      ValueError: malformed affinity, n_neighbors < 1 or intensities of the wrong length.
    """
    if int(n_neighbors) != n_neighbors or n_neighbors < 1:
        raise ValueError(f"n_neighbors must be a positive integer, got {n_neighbors!r}")
    a = influence(affinity)
    if intensities is not None and np.shape(intensities) != (a.shape[0],):
        raise ValueError(
            f"intensities must have shape ({a.shape[0]},) to match the affinity, got "
            f"{np.shape(intensities)}"
        )
    bin_ = binarize_affinity(a, int(n_neighbors))
    bin_, hops, root = connect_components(bin_)
    _, level, rank = refine_graph(a, bin_, hops, root)
    return skeleton_from_parents(find_parents(a, bin_, level, rank))


def prune(
    skeleton: Skeleton, intensities: Any, threshold: float = PRUNE_THRESHOLD
) -> tuple[Skeleton, np.ndarray]:
    """Drops low-intensity keypoints (alpha < threshold), keeping a tree over all K indices.

    Every keypoint is re-attached to its nearest kept ancestor, so kept keypoints form a tree
    among themselves and pruned ones become leaves hanging off it (to be hidden or ignored).
    The root is always kept: forward kinematics starts there.

    Args:
      skeleton: the tree from `extract_skeleton`.
      intensities: (K,) mean intensity alpha of every keypoint.
      threshold: keypoints with alpha < threshold are pruned (0.2 as in the paper's figures).

    Returns:
      (pruned skeleton, keep (K,) bool).
    """
    alpha = np.asarray(intensities, dtype=np.float64)
    if alpha.shape != (skeleton.num_keypoints,):
        raise ValueError(
            f"intensities must have shape ({skeleton.num_keypoints},), got {alpha.shape}"
        )
    keep = alpha >= threshold
    keep[skeleton.root] = True
    parents = np.array(skeleton.parents)
    new_parents = parents.copy()
    for k in skeleton.order[1:]:  # parents before children: new_parents[p] already resolved
        p = parents[k]
        new_parents[k] = p if keep[p] else new_parents[p]
    return skeleton_from_parents(new_parents), keep


def skin_weights(
    vertices: Any,
    joints: Any,
    skeleton: Skeleton,
    intensities: Any = None,
    threshold: float = PRUNE_THRESHOLD,
    sigma_scale: float = 0.5,
) -> np.ndarray:
    """Distance-based skin weights, Algorithm 2 (appendix A.4).

    Keypoints with alpha < threshold are pruned and their children re-attached (`prune`). Each
    kept non-root keypoint i has a bone at the midpoint of i and its parent p (the root's bone is
    the root itself). A vertex belongs to its nearest bone, and its weight is shared between the
    bone's two ends by a gaussian kernel on the distance to each, exp(-d^2 / (2 sigma^2)),
    normalised, with sigma = sigma_scale * |mu_i - mu_p| (half the bone length by default, so a
    vertex at one end follows that end's joint and the middle blends evenly). A vertex nearest
    the root's bone gets weight 1 on the root.

    Args:
      vertices: (V, 3) mesh vertices.
      joints: (K, 3) keypoint positions mu (or (K, 4) keypoints, alpha in the last column, used
        as intensities when `intensities` is None).
      skeleton: the tree over the K keypoints.
      intensities: optional (K,) alpha; None keeps every keypoint unless `joints` carries it.
      threshold: pruning threshold on alpha.
      sigma_scale: kernel width as a fraction of the bone length.

    Returns:
      (V, K) float32 weights, rows summing to 1, zero on pruned keypoints.
    """
    p = np.asarray(vertices, dtype=np.float64)
    x = np.asarray(joints, dtype=np.float64)
    num = skeleton.num_keypoints
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"vertices must have shape (V, 3), got {p.shape}")
    if x.shape not in ((num, 3), (num, 4)):
        raise ValueError(f"joints must have shape ({num}, 3) or ({num}, 4), got {x.shape}")
    if intensities is None and x.shape[1] == 4:
        intensities = x[:, 3]
    mu = x[:, :3]
    alpha = np.ones(num) if intensities is None else intensities
    pruned, keep = prune(skeleton, alpha, threshold)
    parents = np.array(pruned.parents)
    bones = 0.5 * (mu + mu[parents])  # the root's "bone" is mu_root itself
    dist = np.linalg.norm(p[:, None, :] - bones[None], axis=-1)  # (V, K)
    dist[:, ~keep] = np.inf
    child = np.argmin(dist, axis=1)  # (V,)
    parent = parents[child]
    bone_length = np.linalg.norm(mu[child] - mu[parent], axis=-1)
    sigma = np.maximum(sigma_scale * bone_length, 1e-6)
    d_child = np.sum((p - mu[child]) ** 2, axis=-1)
    d_parent = np.sum((p - mu[parent]) ** 2, axis=-1)
    # Normalised gaussians exp(-d/2s^2) of the two ends, written as a stable logistic.
    w_child = 1.0 / (1.0 + np.exp(np.clip((d_child - d_parent) / (2 * sigma**2), -700, 700)))
    w_child = np.where(child == parent, 1.0, w_child)
    weights = np.zeros((len(p), num))
    rows = np.arange(len(p))
    np.add.at(weights, (rows, parent), 1.0 - w_child)
    np.add.at(weights, (rows, child), w_child)
    return weights.astype(np.float32)


def linear_blend_skinning(
    vertices: Any,
    weights: Any,
    transforms: Any = None,
    *,
    rotations: Any = None,
    translations: Any = None,
) -> jnp.ndarray:
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
