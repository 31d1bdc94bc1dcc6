"""Skeleton extraction (Algorithm 1), pruning, skin weights (Algorithm 2), LBS and the CLI."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from nmjax import atomic, cli, losses
from nmjax import keypoints as kp_lib
from nmjax.geometry import linear_blend_skinning
from nmjax.run_folder import pruned_skeleton
from nmjax.skeleton import (
    Skeleton,
    algorithm1_parents,
    extract_skeleton,
    find_parents,
    influence,
    load_skeleton,
    prune,
    skeleton_from_parents,
    skin_weights,
)
from nmjax.train.trained import extract_run_skeleton

# Known trees as parent arrays (root is its own parent).
CHAIN = [0, 0, 1, 2, 3, 4, 5, 6, 7]
STAR = [0] * 8
BINARY = [0] + [(k - 1) // 2 for k in range(1, 15)]
# wrist 0 - palm 1 - five fingers of three joints each.
HAND = [0, 0] + [p for f in range(5) for p in (1, 2 + 3 * f, 3 + 3 * f)]
TREES = {"chain": CHAIN, "star": STAR, "binary": BINARY, "hand": HAND}


def tree_affinity(parents, rng, num_matrices=2, noise=0.0):
    """Softmax-like affinities of a tree: each row prefers its parent, then its children."""
    num = len(parents)
    a = np.full((num_matrices, num, num), 0.01)
    for k, p in enumerate(parents):
        if k != p:
            a[:, k, p] = 1.0
            a[:, p, k] = 0.5
    a += noise * rng.random(a.shape)
    a[:, np.arange(num), np.arange(num)] = 0.0
    return (a / a.sum(axis=-1, keepdims=True)).astype(np.float32)


def permute_tree(parents, perm):
    """Relabels keypoint k as perm[k]."""
    out = np.empty(len(parents), dtype=np.int64)
    out[np.asarray(perm)] = np.asarray(perm)[np.asarray(parents)]
    return out


def tree_distances(parents):
    """All-pairs hop distances of a tree by Floyd-Warshall."""
    num = len(parents)
    d = np.full((num, num), np.inf)
    np.fill_diagonal(d, 0.0)
    for k, p in enumerate(parents):
        if k != p:
            d[k, p] = d[p, k] = 1.0
    for m in range(num):
        d = np.minimum(d, d[:, m : m + 1] + d[m : m + 1, :])
    return d


def reroot(parents, root):
    """Parents of the same undirected tree hung from `root`."""
    num = len(parents)
    adj = [set() for _ in range(num)]
    for k, p in enumerate(parents):
        if k != p:
            adj[k].add(p)
            adj[p].add(k)
    out, stack = [-1] * num, [root]
    out[root] = root
    while stack:
        k = stack.pop()
        for c in adj[k]:
            if out[c] == -1:
                out[c] = k
                stack.append(c)
    return out


def edge_set(parents):
    return {tuple(sorted((k, int(p)))) for k, p in enumerate(parents) if k != p}


def assert_valid_tree(skeleton: Skeleton, num: int):
    parents = np.array(skeleton.parents)
    assert parents.shape == (num,)
    assert np.all((parents >= 0) & (parents < num))
    assert parents[skeleton.root] == skeleton.root
    assert np.sum(parents == np.arange(num)) == 1
    for k in range(num):  # every keypoint reaches the root within K steps (no cycles)
        node = k
        for _ in range(num):
            node = parents[node]
        assert node == skeleton.root
    assert sorted(skeleton.order) == list(range(num)) and skeleton.order[0] == skeleton.root
    position = {k: i for i, k in enumerate(skeleton.order)}
    assert all(position[parents[k]] < position[k] for k in range(num) if k != skeleton.root)
    depths = [0] * num
    for k in skeleton.order[1:]:
        depths[k] = depths[parents[k]] + 1
    assert skeleton.depth == max(depths)


# Algorithm 1 links every keypoint to exactly N others, so with N >= 2 a leaf gets a second
# edge and the tree need not be the one the strongest entries follow; with N = 1 the links of a
# tree affinity are the tree. The filtered variant drops the weak second links at any N.
RECOVERING = [("algorithm1", 1), ("filtered", 1), ("filtered", 2), ("filtered", 3)]


@pytest.mark.parametrize("name", sorted(TREES))
@pytest.mark.parametrize(("method", "n_neighbors"), RECOVERING)
def test_known_trees_are_recovered_with_their_centre_as_root(name, method, n_neighbors):
    rng = np.random.default_rng(n_neighbors)
    perm = rng.permutation(len(TREES[name]))
    parents = permute_tree(TREES[name], perm)
    affinity = tree_affinity(parents, rng, noise=0.005)
    skeleton = extract_skeleton(affinity, n_neighbors, method=method)
    sums = tree_distances(parents).sum(axis=1)
    centre = int(np.flatnonzero(sums == sums.min())[0])
    assert skeleton.root == centre
    assert edge_set(skeleton.parents) == edge_set(parents)
    assert list(skeleton.parents) == reroot(parents, centre)
    assert_valid_tree(skeleton, len(parents))


def six_node_affinity():
    """Rows of I (zero diagonal) whose top-2 links make the graph 0-1, 0-4, 0-5, 1-2, 1-3, 1-4,
    2-3, 4-5; the strongest entries follow the tree 0-1, 1-2, 2-3, 1-4, 4-5."""
    rows = {
        0: {1: 0.6, 4: 0.2, 2: 0.1, 3: 0.05, 5: 0.05},
        1: {0: 0.4, 2: 0.3, 4: 0.2, 3: 0.05, 5: 0.05},
        2: {1: 0.5, 3: 0.4, 0: 0.05, 4: 0.03, 5: 0.02},
        3: {2: 0.7, 1: 0.2, 0: 0.05, 4: 0.03, 5: 0.02},
        4: {1: 0.5, 5: 0.4, 0: 0.05, 2: 0.03, 3: 0.02},
        5: {4: 0.8, 0: 0.1, 1: 0.05, 2: 0.03, 3: 0.02},
    }
    a = np.zeros((6, 6))
    for i, row in rows.items():
        for j, v in row.items():
            a[i, j] = v
    return a


def test_algorithm1_six_nodes_by_hand():
    # Step 2 (top-2 links, symmetrised): 0:{1,4,5} 1:{0,2,3,4} 2:{1,3} 3:{1,2} 4:{0,1,5} 5:{0,4}.
    # Step 3, summed hop distances: [7, 6, 9, 9, 7, 10]; connected.
    # Step 5, equal sums: (0, 4) with common neighbours 1 and 5: I[1,0]=.4 > I[1,4]=.2 -> edge
    #   (1,4) +1e-5; I[5,0]=.1 < I[5,4]=.8 -> edge (5,0) +1e-5. (2, 3), common neighbour 1:
    #   I[1,2]=.3 > I[1,3]=.05 -> edge (1,3) +1e-5.
    # Step 6, weighted sums (e = 1e-5): node 1: 1 + 1 + (1+e) + (1+e) + (2+e) = 6 + 3e, the
    #   smallest: root 1, ranks r = [1, 0, 1, 1+e, 1+e, 2+e].
    # Step 7: 0 -> 1 (its only nearer neighbour); 2 -> 1; 3: neighbours 1 (gap -1-e), 2 (gap -e,
    #   nearer in rank) -> 2; 4: neighbours 0 (gap -e), 1 (gap -1-e) -> 0; 5: 0 (gap -1-e),
    #   4 (gap -1) -> 4. No equal ranks among neighbours.
    # Step 8, distances along the tree: [1, 0, 1, 2, 2, 3] -> order 1, 0, 2, 3, 4, 5.
    skeleton = extract_skeleton(six_node_affinity(), 2)
    assert skeleton == Skeleton(
        parents=(1, 1, 1, 2, 0, 4), root=1, order=(1, 0, 2, 3, 4, 5), depth=3
    )
    # The filtered variant drops the links at or below the row mean (0.2): the tree the strongest
    # entries follow, 4 under 1.
    filtered = extract_skeleton(six_node_affinity(), 2, method="filtered")
    assert filtered.parents == (1, 1, 1, 2, 1, 4)


def test_algorithm1_same_rank_rule_by_hand():
    # N = 1: 0 -> 1, 1 -> 2, 2 -> 0, 3 -> 1, 4 -> 0: graph 0-1, 0-2, 1-2, 1-3, 0-4.
    # Hop sums [5, 5, 6, 8, 8]. Step 5: (0, 1) tie, common neighbour 2, I[2,0]=.5 > I[2,1]=.3 ->
    #   edge (2,1) +1e-5; (3, 4) tie without a common neighbour.
    # Root 0 (sum 5 against 5 + 1e-5 for node 1); ranks [0, 1, 1, 2, 1].
    # Step 7: 1 and 2 are neighbours of equal rank 1 whose shared nearer neighbour is m = 0.
    #   For k = 1, n = 2: I[0,2]=.3 > I[0,1]=.6? no -> 1 keeps 0. For k = 2, n = 1: I[0,1] >
    #   I[0,2] -> 2 hangs below 1. 3 -> 1, 4 -> 0.
    # Step 8: tree distances [0, 1, 2 + 1e-5, 2, 1] -> order 0, 1, 4, 3, 2.
    a = np.zeros((5, 5))
    a[0, [1, 2, 3, 4]] = [0.6, 0.3, 0.05, 0.05]
    a[1, [2, 0, 3, 4]] = [0.5, 0.3, 0.1, 0.1]
    a[2, [0, 1, 3, 4]] = [0.5, 0.3, 0.1, 0.1]
    a[3, [1, 0, 2, 4]] = [0.7, 0.1, 0.1, 0.1]
    a[4, [0, 1, 2, 3]] = [0.7, 0.1, 0.1, 0.1]
    skeleton = extract_skeleton(a, 1)
    assert skeleton == Skeleton(parents=(0, 0, 1, 1, 0), root=0, order=(0, 1, 4, 3, 2), depth=2)
    # Step 7 alone on the same graph and ranks: when the shared ancestor prefers 2, 1 hangs below 2.
    bin_ = np.zeros((5, 5), dtype=bool)
    for i, j in [(0, 1), (0, 2), (1, 2), (1, 3), (0, 4)]:
        bin_[i, j] = bin_[j, i] = True
    rank = np.array([0.0, 1, 1, 2, 1])
    assert list(algorithm1_parents(a, bin_, rank, 0)) == [0, 0, 1, 1, 0]
    a[0, 1], a[0, 2] = 0.3, 0.6
    assert list(algorithm1_parents(a, bin_, rank, 0)) == [0, 2, 0, 1, 0]


def test_hand_root_is_the_palm_and_depth_is_finger_length():
    for method, n in (("algorithm1", 1), ("filtered", 2)):
        skeleton = extract_skeleton(tree_affinity(HAND, np.random.default_rng(0)), n, method=method)
        assert skeleton.root == 1
        assert skeleton.depth == 3
        assert skeleton.parents[2::3] == (1,) * 5


@pytest.mark.parametrize(("method", "n_neighbors"), [("algorithm1", 1), ("filtered", 2)])
def test_disconnected_affinity_gives_one_tree_keeping_each_parts_edges(method, n_neighbors):
    rng = np.random.default_rng(0)
    first, second = CHAIN, [0, 0, 0, 1, 1]  # a 9-chain and a small tree, no affinity between
    num = len(first) + len(second)
    a = np.zeros((2, num, num))
    a[:, : len(first), : len(first)] = tree_affinity(first, rng)
    a[:, len(first) :, len(first) :] = tree_affinity(second, rng)
    skeleton = extract_skeleton(a, n_neighbors, method=method)
    assert_valid_tree(skeleton, num)
    shifted = [p + len(first) for p in second]
    expected = edge_set(first) | {tuple(sorted((k + len(first), p))) for k, p in enumerate(shifted)}
    expected = {e for e in expected if e[0] != e[1]}
    edges = edge_set(skeleton.parents)
    assert expected <= edges
    bridge = edges - expected
    assert len(bridge) == 1
    ((i, j),) = bridge
    assert i < len(first) <= j
    # Root of the bigger part (the chain's middle) joined to the small part's pseudo root (its
    # most central keypoint, 1: summed distances 6, 5, 8, 8, 8).
    assert skeleton.root == 4 and bridge == {(4, len(first) + 1)}


def test_isolated_uniform_rows_are_still_attached():
    a = np.ones((6, 6))  # all rows uniform: no neighbour above the row mean
    skeleton = extract_skeleton(a, 2, method="filtered")
    assert_valid_tree(skeleton, 6)
    assert skeleton.root == 0 and skeleton.depth == 1
    assert_valid_tree(extract_skeleton(a, 2), 6)


def test_degenerate_affinities():
    # All-zero rows: Algorithm 1 links each node to the two lowest other indices (0-1, 0-2, 1-2,
    # 0-3, 1-3, 0-4, 1-4); hop sums [4, 4, 6, 6, 6]. Ties (0,1), (2,3), (2,4), (3,4) with equal
    # (zero) influences lengthen the edges towards the lower index of each pair: (0,2) by 3e-5,
    # (0,3) and (1,2) by 2e-5, (0,4) and (1,3) by 1e-5. Weighted sums: 0 -> 4 + 6e-5, 1 -> 4 +
    # 3e-5: root 1, ranks [1, 0, 1+2e-5, 1+1e-5, 1]; 2 and 3 take 0 (nearest in rank), 4 takes 1.
    assert extract_skeleton(np.zeros((2, 5, 5))).parents == (1, 1, 0, 0, 1)
    assert extract_skeleton(np.zeros((2, 5, 5)), method="filtered").parents == (0, 0, 0, 0, 0)
    single = extract_skeleton(np.zeros((1, 1)))
    assert single == Skeleton(parents=(0,), root=0, order=(0,), depth=0)


@settings(max_examples=60, deadline=None)
@given(
    num=st.integers(3, 40),
    num_matrices=st.integers(1, 3),
    n_neighbors=st.integers(1, 4),
    sparsity=st.sampled_from([0.0, 0.5, 0.9]),
    method=st.sampled_from(["algorithm1", "filtered"]),
    seed=st.integers(0, 2**31 - 1),
)
def test_random_affinities_always_give_a_deterministic_valid_tree(
    num, num_matrices, n_neighbors, sparsity, method, seed
):
    rng = np.random.default_rng(seed)
    a = rng.random((num_matrices, num, num)) * (rng.random((num_matrices, num, num)) >= sparsity)
    if rng.random() < 0.3:
        a = np.round(a, 1)  # many exact ties
    skeleton = extract_skeleton(a, n_neighbors, method=method)
    assert_valid_tree(skeleton, num)
    assert extract_skeleton(a.copy(), n_neighbors, method=method) == skeleton


def test_same_rank_cycles_are_broken_into_a_tree():
    # Ranks: root 0, then 1, 2, 3 all at rank 1, all linked to each other and to 0. The shared
    # nearer neighbour is m = 0 for every pair, so I[0, .] = [., .5, .3, .2] decides, and the last
    # same-rank neighbour that m prefers wins: 1 keeps 0; 2 takes 1; 3 takes 1, then 2. One m
    # cannot close a cycle (it would need I[0,2] > I[0,1] > I[0,3] > I[0,2]).
    bin_ = np.ones((4, 4), dtype=bool)
    np.fill_diagonal(bin_, False)
    a = np.zeros((4, 4))
    a[0, 1:] = [0.5, 0.3, 0.2]
    parents = algorithm1_parents(a, bin_, np.array([0.0, 1, 1, 1]), 0)
    assert list(parents) == [0, 0, 1, 2]
    # Three same-rank nodes whose shared nearer neighbours differ can choose each other in a
    # cycle; the lowest index of the cycle then takes its nearer neighbour.
    bin_ = np.zeros((7, 7), dtype=bool)
    edges = [(0, 4), (0, 5), (0, 6), (1, 2), (2, 3), (3, 1), (1, 4), (2, 4), (2, 5), (3, 5)]
    edges += [(3, 6), (1, 6)]
    for i, j in edges:
        bin_[i, j] = bin_[j, i] = True
    rank = np.array([0.0, 2, 2, 2, 1, 1.1, 1.2])
    a = np.zeros((7, 7))
    a[4, 2], a[4, 1] = 0.9, 0.1  # k=1, n=2: m = 4 (shared, smallest rank) prefers 2: 1 -> 2
    a[5, 3], a[5, 2] = 0.9, 0.1  # k=2, n=3: m = 5 prefers 3: 2 -> 3
    a[6, 1], a[6, 3] = 0.9, 0.1  # k=3, n=1: m = 6 prefers 1: 3 -> 1, closing 1 -> 2 -> 3 -> 1
    parents = algorithm1_parents(a, bin_, rank, 0)
    assert_valid_tree(skeleton_from_parents(parents), 7)
    # 1, the lowest of the cycle, takes its neighbour nearest in rank among those nearer the
    # root: 6 (rank 1.2) before 4 (rank 1).
    assert list(parents[1:4]) == [6, 3, 1]


def test_bad_method_and_order_are_named():
    with pytest.raises(ValueError, match="unknown skeleton method"):
        extract_skeleton(np.ones((3, 3)), method="mst")
    with pytest.raises(ValueError, match="topological order"):
        skeleton_from_parents([0, 0, 1], order=[0, 2, 1])
    assert skeleton_from_parents([0, 0, 0], order=[0, 2, 1]).order == (0, 2, 1)


def test_same_rank_rule_adopts_the_neighbour_the_shared_ancestor_prefers():
    # 0 is the root; 1 and 2 both on level 1 and linked to each other; rank[1] < rank[2].
    bin_ = np.zeros((4, 4), dtype=bool)
    for i, j in [(0, 1), (0, 2), (1, 2), (0, 3)]:
        bin_[i, j] = bin_[j, i] = True
    level, rank = np.array([0, 1, 1, 1]), np.array([0, 1, 2, 3])
    a = np.zeros((4, 4))
    a[0, 1], a[0, 2] = 0.6, 0.3  # the root prefers 1: 2 hangs below 1
    assert list(find_parents(a, bin_, level, rank)) == [0, 0, 1, 0]
    a[0, 1], a[0, 2] = 0.3, 0.6  # the root prefers 2: 2 stays a child of the root
    assert list(find_parents(a, bin_, level, rank)) == [0, 0, 0, 0]


def test_normal_parent_is_the_youngest_higher_rank_neighbour():
    # 3 on level 2 links to 1 and 2 on level 1; 2 is ranked later (younger) than 1.
    bin_ = np.zeros((4, 4), dtype=bool)
    for i, j in [(0, 1), (0, 2), (1, 3), (2, 3)]:
        bin_[i, j] = bin_[j, i] = True
    parents = find_parents(np.zeros((4, 4)), bin_, np.array([0, 1, 1, 2]), np.array([0, 1, 2, 3]))
    assert list(parents) == [0, 0, 0, 2]


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="affinity must have shape"):
        extract_skeleton(np.ones((3, 4)))
    with pytest.raises(ValueError, match="non-negative"):
        extract_skeleton(-np.ones((3, 3)))
    with pytest.raises(ValueError, match="n_neighbors"):
        extract_skeleton(np.ones((3, 3)), 0)
    with pytest.raises(ValueError, match="intensities"):
        extract_skeleton(np.ones((3, 3)), 2, intensities=np.ones(4))
    with pytest.raises(ValueError, match="cycle"):
        skeleton_from_parents([0, 2, 1])
    with pytest.raises(ValueError, match="exactly one root"):
        skeleton_from_parents([0, 1, 1])


def test_skeleton_and_graph_losses_combine_the_affinities_with_the_one_influence():
    """Algorithm 1 (NumPy, float64) and the graph losses (JAX) share `keypoints.influence`: the
    skeleton's influence of a detector affinity equals the losses', and every graph loss gives
    the same value on the skeleton's (K, K) as on the (N, K, K) stack."""
    rng = np.random.default_rng(3)
    affinity = kp_lib.affinity_from_params(jnp.asarray(rng.normal(size=(2, 5, 4)), jnp.float32))
    combined = kp_lib.influence(affinity)  # the losses' (JAX) call site
    assert isinstance(combined, jax.Array) and combined.shape == (5, 5)
    from_skeleton = influence(np.asarray(affinity))
    assert from_skeleton.dtype == np.float64
    np.testing.assert_array_equal(from_skeleton, np.asarray(combined, np.float64))
    x = jnp.asarray(rng.uniform(-1, 1, (1, 4, 5, 4)), jnp.float32)
    for term in (losses.graph_local, losses.graph_time, losses.graph_trajectory):
        np.testing.assert_allclose(
            term(x, affinity), term(x, jnp.asarray(from_skeleton, jnp.float32)), rtol=1e-6
        )
    # NumPy in, NumPy out in the same dtype: float64 ties stay exact for Algorithm 1.
    stack = rng.random((3, 4, 4))
    same = kp_lib.influence(stack)
    assert isinstance(same, np.ndarray) and same.dtype == np.float64
    np.testing.assert_array_equal(same, np.maximum(np.maximum(stack[0], stack[1]), stack[2]))


def test_save_and_load_round_trip(tmp_path):
    skeleton = skeleton_from_parents(BINARY)
    skeleton.save(tmp_path / "s.json", intensities=np.arange(15) / 15)
    assert load_skeleton(tmp_path / "s.json") == skeleton
    tree_ordered = extract_skeleton(six_node_affinity())  # an order that is not breadth first
    tree_ordered.save(tmp_path / "t.json")
    assert load_skeleton(tmp_path / "t.json") == tree_ordered
    data = json.loads((tmp_path / "s.json").read_text())
    assert data["order"] == list(skeleton.order) and len(data["intensities"]) == 15
    with pytest.raises(FileNotFoundError, match="nmjax extract-skeleton"):
        load_skeleton(tmp_path / "missing.json")
    atomic.write_json(tmp_path / "bad.json", {"parents": [1, 0]})
    with pytest.raises(ValueError, match="bad.json"):
        load_skeleton(tmp_path / "bad.json")


def test_prune_reattaches_children_to_nearest_kept_ancestor():
    skeleton = skeleton_from_parents([0, 0, 1, 2, 3, 1])  # 0-1-2-3-4, 1-5
    pruned, keep = prune(skeleton, [0.1, 0.9, 0.05, 0.1, 0.8, 0.5])
    assert keep.tolist() == [True, True, False, False, True, True]  # root always kept
    assert pruned.parents == (0, 0, 1, 1, 1, 1)


def two_bone_arm():
    joints = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    return joints, skeleton_from_parents([0, 0, 1])


def test_skin_weights_match_algorithm_2_by_hand():
    joints, skeleton = two_bone_arm()
    vertices = np.array([[0.6, 0.1, 0.0], [1.9, -0.2, 0.0], [-0.3, 0.0, 0.0]])
    w = skin_weights(vertices, joints, skeleton)
    # Vertex 0: nearest bone is 0-1 (midpoint 0.5), sigma = 0.5: weights e^{-d^2/0.5}.
    g = np.exp(-np.array([0.37, 0.17]) / 0.5)
    np.testing.assert_allclose(w[0], [g[0] / g.sum(), g[1] / g.sum(), 0.0], rtol=1e-5)
    g = np.exp(-np.array([0.81 + 0.04, 0.01 + 0.04]) / 0.5)  # bone 1-2
    np.testing.assert_allclose(w[1], [0.0, g[0] / g.sum(), g[1] / g.sum()], rtol=1e-5)
    np.testing.assert_allclose(w[2], [1.0, 0.0, 0.0])  # nearest the root's bone


def test_skin_weights_rows_sum_to_one_and_skip_pruned_keypoints():
    rng = np.random.default_rng(0)
    skeleton = extract_skeleton(tree_affinity(HAND, rng))
    joints = rng.normal(size=(len(HAND), 4))
    joints[:, 3] = rng.random(len(HAND))
    w = skin_weights(rng.normal(size=(200, 3)) * 3, joints, skeleton)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=1e-6)
    assert np.all(w >= 0)
    dropped = (joints[:, 3] < 0.2) & (np.arange(len(HAND)) != skeleton.root)
    assert dropped.any() and np.all(w[:, dropped] == 0)


def lbs_reference(vertices, weights, transforms):
    out = np.zeros(transforms.shape[:-3] + vertices.shape)
    for k in range(weights.shape[1]):
        moved = np.einsum("...ij,vj->...vi", transforms[..., k, :3, :3], vertices)
        out += weights[:, k, None] * (moved + transforms[..., k, None, :3, 3])
    return out


def random_transforms(rng, shape):
    t = np.zeros(shape + (4, 4))
    t[..., :3, :3] = (
        Rotation.random(int(np.prod(shape)), random_state=rng).as_matrix().reshape(shape + (3, 3))
    )
    t[..., :3, 3] = rng.normal(size=shape + (3,))
    t[..., 3, 3] = 1.0
    return t


def test_lbs_identity_rigid_and_general():
    rng = np.random.default_rng(1)
    joints, skeleton = two_bone_arm()
    vertices = rng.normal(size=(50, 3))
    w = skin_weights(vertices, joints, skeleton)
    identity = np.broadcast_to(np.eye(4), (3, 4, 4))
    np.testing.assert_allclose(linear_blend_skinning(vertices, w, identity), vertices, atol=1e-5)
    rigid = random_transforms(rng, (1,))[0]
    moved = linear_blend_skinning(vertices, w, np.broadcast_to(rigid, (3, 4, 4)))
    np.testing.assert_allclose(moved, vertices @ rigid[:3, :3].T + rigid[:3, 3], atol=1e-5)
    batch = random_transforms(rng, (2, 3))
    expected = lbs_reference(vertices, w.astype(np.float64), batch)
    got = jax.jit(linear_blend_skinning)(vertices, w, batch)
    assert got.shape == (2, 50, 3)
    np.testing.assert_allclose(got, expected, atol=1e-4)
    split = linear_blend_skinning(
        vertices, w, rotations=batch[..., :3, :3], translations=batch[..., :3, 3]
    )
    np.testing.assert_allclose(split, expected, atol=1e-4)
    with pytest.raises(ValueError, match="either transforms"):
        linear_blend_skinning(vertices, w)


def fake_run(path, parents, rng, grid=8):
    num = len(parents)
    atomic.save_npy(path / "affinity.npy", tree_affinity(parents, rng))
    voxels = np.zeros((grid, grid, grid), dtype=np.float32)
    voxels[2:6, 3:5, 1:7] = 1.0
    keypoints = np.concatenate([rng.uniform(-1, 1, (num, 3)), rng.random((num, 1))], axis=1)
    atomic.save_npz(
        path / "keypoint_stats.npz",
        intensities=keypoints[:, 3].astype(np.float32),
        rest_positions=keypoints[:, :3].astype(np.float32),
        example_voxels=voxels,
        example_keypoints=keypoints.astype(np.float32),
    )
    return keypoints


def test_cli_writes_skeleton_json_and_figure(tmp_path, capsys):
    run = tmp_path / "skel-synth-hand-0"
    run.mkdir()
    keypoints = fake_run(run, HAND, np.random.default_rng(0))
    assert cli.main(["extract-skeleton", "--run", str(run), "--neighbors", "1"]) == 0
    assert "root 1" in capsys.readouterr().out
    assert json.loads((run / "skeleton.json").read_text())["method"] == "algorithm1"
    assert cli.main(["extract-skeleton", "--run", str(run), "--method", "filtered"]) == 0
    assert "root 1" in capsys.readouterr().out
    data = json.loads((run / "skeleton.json").read_text())
    assert data["method"] == "filtered"
    assert data["parents"] == reroot(HAND, 1) and data["root"] == 1
    assert data["order"][0] == 1 and data["depth"] == 3
    np.testing.assert_allclose(data["intensities"], keypoints[:, 3], rtol=1e-6)
    np.testing.assert_allclose(data["rest_positions"], keypoints[:, :3], rtol=1e-6)
    assert data["keep"] == [bool(a >= 0.2 or k == 1) for k, a in enumerate(keypoints[:, 3])]
    assert load_skeleton(run / "skeleton.json").parents == tuple(data["parents"])
    png = (run / "figures" / "skeleton.png").read_bytes()
    assert png.startswith(b"\x89PNG") and len(png) > 5000


def test_pruned_skeleton_is_what_extract_skeleton_stored_at_its_threshold(tmp_path):
    """`run_folder.pruned_skeleton` (what evaluate, view and the generation measures read)
    returns the kept nodes and pruned tree skeleton.json stores, here extracted with a non-default
    `--prune-threshold`, not a new pruning of the stored intensities at the default 0.2."""
    run = tmp_path / "skel-synth-hand-0"
    run.mkdir()
    alpha = fake_run(run, HAND, np.random.default_rng(0))[:, 3]
    assert pruned_skeleton(run) is None  # not extracted yet
    threshold = 0.6
    argv = ["extract-skeleton", "--run", str(run), "--prune-threshold", str(threshold)]
    assert cli.main(argv) == 0
    stored = json.loads((run / "skeleton.json").read_text())
    tree = load_skeleton(run / "skeleton.json")
    parents, keep = pruned_skeleton(run)
    expected = (alpha >= threshold) | (np.arange(len(HAND)) == tree.root)
    assert keep.tolist() == stored["keep"] == expected.tolist()
    assert parents.tolist() == stored["pruned_parents"]
    assert parents.tolist() == list(prune(tree, alpha, threshold)[0].parents)
    assert keep.sum() < prune(tree, alpha)[1].sum()  # the default would keep more nodes
    assert stored["prune_threshold"] == threshold


def test_extract_run_skeleton_names_missing_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        extract_run_skeleton(tmp_path / "nope")
    with pytest.raises(FileNotFoundError, match="affinity.npy"):
        extract_run_skeleton(tmp_path)
    fake_run(tmp_path, CHAIN, np.random.default_rng(0))
    atomic.save_npz(tmp_path / "keypoint_stats.npz", intensities=np.ones(3))
    with pytest.raises(ValueError, match="lacks"):
        extract_run_skeleton(tmp_path)
