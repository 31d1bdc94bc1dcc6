"""Skeleton extraction (paper Sec. 4, appendix A.3, Algorithm 1) and skinning (A.4, Algorithm 2).

Runs between the phases on the learned affinity, in NumPy/SciPy: the result is a kinematic tree
over all K keypoints (`Skeleton`), written as `skeleton.json` into the phase-1 run folder. The
skinning half (`skin_weights`, Algorithm 2) binds a target mesh to the tree for retargeting; the
skinning itself is `nmjax.geometry.linear_blend_skinning`.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
from scipy.sparse import csgraph

from nmjax import atomic, keypoints
from nmjax.parents import parents_from_external

NO_PATH = 1e4  # Algorithm 1: hop distance written for "no path" between two keypoints
PRUNE_THRESHOLD = 0.2  # keypoints with mean intensity alpha below this are pruned (paper figures)
DEFAULT_NEIGHBORS = 2  # N of Algorithm 1: the number of neighbours each keypoint links to
# "algorithm1": the paper's Algorithm 1 (docs/architecture.md §7), the default; "filtered": weak
# links dropped and a hop-level ranking (see `extract_skeleton`).
METHODS = ("algorithm1", "filtered")


@dataclasses.dataclass(frozen=True)
class Skeleton:
    """A rooted kinematic tree over K keypoints.

    Attributes:
      parents: (K,) parent of every keypoint; the root is its own parent.
      root: index of the root keypoint.
      order: (K,) topological order, root first, every parent before its children (Algorithm 1's
        order by distance from the root along the tree, or breadth first, children by index).
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
        atomic.write_json(path, payload)


def skeleton_from_parents(parents: Any, order: Any = None) -> Skeleton:
    """Builds a `Skeleton` from a parent array, checking that it is a single rooted tree.

    Args:
      parents: (K,) ints; exactly one entry is its own parent (the root).
      order: optional (K,) topological order to keep (a permutation, root first, every parent
        before its children); None orders breadth first, children by index.

    Raises:
      ValueError: indices out of range, not exactly one root, a cycle, or an `order` that is not
        a topological order of the tree.
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
    bfs, depths = [root], {root: 0}
    for k in bfs:  # breadth first; the list grows while it is walked
        for c in children[k]:
            depths[c] = depths[k] + 1
            bfs.append(c)
    if len(bfs) != num:
        cyclic = sorted(set(range(num)) - set(bfs))
        raise ValueError(f"parents {parents.tolist()} contain a cycle through {cyclic}")
    if order is None:
        order = bfs
    else:
        order = [int(k) for k in order]
        position = {k: i for i, k in enumerate(order)}
        if (
            sorted(order) != list(range(num))
            or order[0] != root
            or any(position[int(parents[k])] > position[k] for k in range(num))
        ):
            raise ValueError(
                f"order {order} is not a topological order of parents {parents.tolist()} (a "
                "permutation starting at the root, every parent before its children)"
            )
    return Skeleton(
        parents=tuple(int(p) for p in parents),
        root=root,
        order=tuple(order),
        depth=max(depths.values()),
    )


def load_skeleton(path: str | os.PathLike) -> Skeleton:
    """Reads a `skeleton.json` written by `Skeleton.save` (or by hand, its root in any of the
    conventions of `nmjax.parents.parents_from_external`) and validates it.

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
    parents = parents_from_external(data["parents"], f"{path} `parents`")
    try:
        skeleton = skeleton_from_parents(parents, data.get("order"))
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from e
    if "root" in data and int(data["root"]) != skeleton.root:
        raise ValueError(f"{path}: root {data['root']} is not the parents' root {skeleton.root}")
    return skeleton


def influence(affinity: Any) -> np.ndarray:
    """Influence max_n A_n of the N learned affinities (docs/architecture.md §7), checked, in
    float64.

    The max is `keypoints.influence`, the graph losses' own; here the input is validated and
    the diagonal (a keypoint's affinity to itself) zeroed.

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
    a = keypoints.influence(a)
    np.fill_diagonal(a, 0.0)
    return a


def binarize_affinity(a: np.ndarray, n_neighbors: int, row_mean_filter: bool = False) -> np.ndarray:
    """BinarizeAffinity of Algorithm 1 (line 1): symmetric neighbourhood matrix A^bin.

    Keypoint i links to its `n_neighbors` strongest keypoints (ties by index; never itself), and
    the links are symmetrised (an edge if either end chose it), so a keypoint can have more than
    N neighbours (a palm with five fingers). That is Algorithm 1 (docs/architecture.md §7, step 2).

    With `row_mean_filter` (the "filtered" method) a link is kept only when its affinity exceeds
    the mean of row i's off-diagonal entries (for softmaxed rows the uniform level 1/(K-1)), so a
    leaf whose row puts all its mass on one neighbour gets no second edge. Not in the paper.

    Args:
      a: (K, K) influence with a zero diagonal.
      n_neighbors: N >= 1.
      row_mean_filter: drop links at or below the row mean.

    Returns:
      (K, K) bool, symmetric, zero diagonal.
    """
    num = a.shape[0]
    bin_ = np.zeros((num, num), dtype=bool)
    if num == 1:
        return bin_
    masked = np.where(np.eye(num, dtype=bool), -np.inf, a)
    # Stable argsort of -a: strongest first, equal values by lower index; the diagonal last.
    ranked = np.argsort(-masked, axis=1, kind="stable")[:, : min(n_neighbors, num - 1)]
    rows = np.arange(num)[:, None]
    chosen = np.ones(ranked.shape, dtype=bool)
    if row_mean_filter:
        chosen = a[rows, ranked] > a.sum(axis=1, keepdims=True) / (num - 1)
    bin_[np.broadcast_to(rows, ranked.shape)[chosen], ranked[chosen]] = True
    return bin_ | bin_.T


def shortest_paths(lengths: np.ndarray) -> np.ndarray:
    """All-pairs shortest path lengths of an undirected graph, NO_PATH where unreachable.

    Floyd-Warshall in NumPy: the distances Dijkstra gives (Algorithm 1 names Dijkstra), without
    scipy.sparse.csgraph's per-call input validation, for graphs of a few dozen nodes.

    Args:
      lengths: (K, K) symmetric non-negative edge lengths, 0 where there is no edge.
    """
    dist = np.where(lengths > 0, lengths, np.inf)
    np.fill_diagonal(dist, 0.0)
    for m in range(len(dist)):
        np.minimum(dist, dist[:, m : m + 1] + dist[m : m + 1, :], out=dist)
    return np.where(np.isfinite(dist), dist, NO_PATH)


def hop_distances(bin_: np.ndarray) -> np.ndarray:
    """Hop distances over the unweighted graph A^bin (Algorithm 1 line 2); NO_PATH where
    unreachable."""
    return shortest_paths(bin_.astype(np.float64))


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
        outside = np.flatnonzero(dist[root] >= NO_PATH)  # the other components
        if outside.size == 0:
            return bin_, dist, root
        k = _argmin_sum(dist, outside)
        bin_[root, k] = bin_[k, root] = True
        dist = hop_distances(bin_)
        root = _argmin_sum(dist, everyone)


# --- Algorithm 1 as published (docs/architecture.md §7 steps 5-8), the default --------------------

# docs/architecture.md §7 step 5: extra length of an edge that breaks a tie of summed distances
TIE_BREAK = 1e-5
RANK_TOL = 1e-9  # distances that differ by less are equal ranks (far below TIE_BREAK)


def tie_break_lengths(a: np.ndarray, bin_: np.ndarray, hops: np.ndarray) -> np.ndarray:
    """RefineGraph's edge lengths (docs/architecture.md §7 step 5): every A^bin edge has length 1;
    for each pair k < k' whose summed hop distances are equal and each node n adjacent to both, the
    edge (n, l) grows by 1e-5, l being the one of k, k' that n has the smaller influence on
    (l = k' if I[n, k] > I[n, k'] else k), so n's preferred keypoint ends up nearer.

    Args:
      a: (K, K) influence I; bin_: (K, K) connected A^bin; hops: (K, K) its hop distances.

    Returns:
      (K, K) symmetric edge lengths, 0 where there is no edge.
    """
    lengths = bin_.astype(np.float64)
    sums = hops.sum(axis=1)
    pairs = np.argwhere(np.triu(sums[:, None] == sums[None, :], k=1))  # (M, 2), k < k'
    if len(pairs):
        m, n = np.nonzero(bin_[pairs[:, 0]] & bin_[pairs[:, 1]])  # n adjacent to both of pair m
        k, k2 = pairs[m, 0], pairs[m, 1]
        far = np.where(a[n, k] > a[n, k2], k2, k)
        np.add.at(lengths, (n, far), TIE_BREAK)
        np.add.at(lengths, (far, n), TIE_BREAK)
    return lengths


def algorithm1_parents(a: np.ndarray, bin_: np.ndarray, rank: np.ndarray, root: int) -> np.ndarray:
    """Lines 14-33 of Algorithm 1 as docs/architecture.md §7 step 7 spells them.

    For each k != root, scanning k's A^bin neighbours n in index order with the current choice p
    and its rank gap g = rank[p] - rank[k] (start: none, g = -1e3):
    - rank[n] < rank[k] and rank[n] - rank[k] > g: take n (the neighbour nearest in rank among
      those nearer the root); equal gap: take n if I[k, n] > I[k, p];
    - rank[n] == rank[k]: m = the neighbour of both n and k with rank[m] < rank[n] and the smallest
      rank[m] (ties by index); take n (g = 0) if m exists and I[m, n] > I[m, k].
    No choice: the parent is the root. Ranks closer than `RANK_TOL` are equal.

    Same-rank choices can in principle close a cycle (k takes n, n takes q, q takes k, each by
    another m); the skeleton must be a tree (docs/architecture.md §7), so each such cycle is broken
    at its lowest index, which gets its best strictly-nearer neighbour instead (the rule without the
    same-rank case).

    Args:
      a: (K, K) influence I; bin_: (K, K) connected A^bin; rank: (K,) weighted distance from
        the root; root: the root.

    Returns:
      (K,) int parents; the root is its own parent.
    """
    num = len(rank)
    r, inf = rank.tolist(), a.tolist()  # Python scalars: K is small, NumPy indexing is slower
    rows, cols = np.nonzero(bin_)  # row-major: each row's neighbours in index order
    neighbours: list[list[int]] = [[] for _ in range(num)]
    for i, j in zip(rows.tolist(), cols.tolist(), strict=True):
        neighbours[i].append(j)
    adjacent = [set(n) for n in neighbours]
    parents, nearer = list(range(num)), [root] * num
    for k in range(num):
        if k == root:
            continue
        p, gap, q, q_gap = -1, -1e3, -1, -1e3  # (p, gap): the rule; (q, q_gap): nearer only
        for n in neighbours[k]:
            diff = r[n] - r[k]
            if diff < -RANK_TOL:
                p, gap = _better(inf[k], n, diff, p, gap)
                q, q_gap = _better(inf[k], n, diff, q, q_gap)
            elif abs(diff) <= RANK_TOL:
                shared = [m for m in neighbours[n] if m in adjacent[k] and r[m] < r[n] - RANK_TOL]
                if shared:
                    m = min(shared, key=lambda m: (r[m], m))
                    if inf[m][n] > inf[m][k]:
                        p, gap = n, 0.0
        parents[k] = root if p < 0 else p
        nearer[k] = root if q < 0 else q
    parents = np.asarray(parents)
    while (cycle := _find_cycle(parents, root)) is not None:
        k = min(cycle)
        parents[k] = nearer[k]
    return parents


def _better(row: list[float], n: int, diff: float, best: int, best_gap: float):
    """(choice, gap) after neighbour n with rank gap `diff` < 0 (step 7's first rule); `row` is
    I[k, :]."""
    if diff > best_gap + RANK_TOL:
        return n, diff
    if abs(diff - best_gap) <= RANK_TOL and row[n] > row[best]:
        return n, diff
    return best, best_gap


def _find_cycle(parents: np.ndarray, root: int) -> list[int] | None:
    """The nodes of one cycle of the parent graph, or None when every node reaches the root."""
    up = parents.tolist()
    state = [0] * len(up)  # 0 unseen, 1 on the current walk, 2 reaches the root
    state[root] = 2
    for start in range(len(up)):
        path, k = [], start
        while state[k] == 0:
            state[k] = 1
            path.append(k)
            k = up[k]
        if state[k] == 1:
            return path[path.index(k) :]
        for j in path:
            state[j] = 2
    return None


def tree_order(skeleton: Skeleton, lengths: np.ndarray) -> np.ndarray:
    """docs/architecture.md §7 step 8: nodes sorted (stably) by their distance from the root along
    the tree, each tree edge as long as in `lengths` (1 for an edge that A^bin lacks)."""
    parents = skeleton.parents
    dist = np.zeros(skeleton.num_keypoints)
    for k in skeleton.order[1:]:  # parents first
        edge = lengths[k, parents[k]]
        dist[k] = dist[parents[k]] + (edge if edge > 0 else 1.0)
    return np.argsort(dist, kind="stable")


# --- the "filtered" method (a variant, not the paper's) ----------------------------------------


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
    affinity: Any,
    n_neighbors: int = DEFAULT_NEIGHBORS,
    intensities: Any = None,
    method: str = "algorithm1",
) -> Skeleton:
    """The kinematic tree over all K keypoints from the learned affinity.

    method="algorithm1" (default): Algorithm 1 as published, step by step as docs/architecture.md
    §7: influence max_n A_n; `binarize_affinity` (each node's top-N links, no threshold,
    symmetrised); `connect_components` (hop distances by Dijkstra, root = argmin of summed
    distances, root to pseudo-root edges until connected); `tie_break_lengths` and weighted Dijkstra
    (RefineGraph); root = argmin of the summed weighted distances, rank = weighted distance from the
    root; `algorithm1_parents` (the neighbour nearest in rank among those nearer the root, same-rank
    rule); `tree_order` (order by distance along the tree).

    method="filtered" (a variant, not the paper's): links at or below the row mean are dropped
    before symmetrising, nodes are ranked by (hop level, affinity-weighted distance
    1 - log(s / max s), index) (`refine_graph`), and `find_parents` takes the youngest
    higher-level neighbour; breadth-first order. Compared with Algorithm 1 on learned affinities
    in experiments/results/archive/alg1_methods.md.

    Both are deterministic (ties go to the lower keypoint index) and return a valid tree.

    Args:
      affinity: (K, K) or (N, K, K) non-negative affinity (contract C10 `affinity.npy`).
      n_neighbors: N, the number of neighbours each keypoint links to.
      intensities: optional (K,) mean keypoint intensities; only checked here (they drive
        `prune` and the skin weights, not the topology).
      method: "algorithm1" or "filtered" (`METHODS`).

    Returns:
      A `Skeleton` over all K keypoints.

    Raises:
      ValueError: malformed affinity, n_neighbors < 1, intensities of the wrong length or an
        unknown method.
    """
    if method not in METHODS:
        raise ValueError(f"unknown skeleton method {method!r}; valid: {', '.join(METHODS)}")
    if int(n_neighbors) != n_neighbors or n_neighbors < 1:
        raise ValueError(f"n_neighbors must be a positive integer, got {n_neighbors!r}")
    a = influence(affinity)
    if intensities is not None and np.shape(intensities) != (a.shape[0],):
        raise ValueError(
            f"intensities must have shape ({a.shape[0]},) to match the affinity, got "
            f"{np.shape(intensities)}"
        )
    filtered = method == "filtered"
    bin_ = binarize_affinity(a, int(n_neighbors), row_mean_filter=filtered)
    bin_, hops, root = connect_components(bin_)
    if filtered:
        _, level, rank = refine_graph(a, bin_, hops, root)
        return skeleton_from_parents(find_parents(a, bin_, level, rank))
    lengths = tie_break_lengths(a, bin_, hops)
    dist = shortest_paths(lengths)
    root = int(np.argmin(dist.sum(axis=1)))
    tree = skeleton_from_parents(algorithm1_parents(a, bin_, dist[root], root))
    return dataclasses.replace(tree, order=tuple(int(k) for k in tree_order(tree, lengths)))


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
