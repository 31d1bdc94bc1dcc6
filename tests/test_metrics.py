import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nmjax import metrics

SETTINGS = settings(max_examples=10, deadline=None)


def np_chamfer(a, b):
    d = ((a[:, None] - b[None]) ** 2).sum(-1)
    return d.min(1).mean() + d.min(0).mean()


_chamfer_jit = jax.jit(metrics.chamfer_distance, static_argnames=("chunk",))


def test_semantic_consistency_perfect_and_accumulated():
    rng = np.random.default_rng(0)
    gt = rng.uniform(-1, 1, (6, 5, 3)).astype(np.float32)
    kp = np.concatenate([gt, np.ones((6, 5, 1), np.float32)], -1)
    assert metrics.semantic_consistency(kp, gt) == pytest.approx(1.0)
    # A permutation of the keypoints is still perfectly consistent.
    assert metrics.semantic_consistency(kp[:, ::-1], gt) == pytest.approx(1.0)
    # Joint 0's nearest keypoint alternates between two keypoints over 4 frames: p = 1/2.
    gt2 = np.zeros((4, 1, 3), np.float32)
    kp2 = np.zeros((4, 2, 4), np.float32)
    kp2[..., 3] = 1
    kp2[:, 0, 0] = [0.1, 0.5, 0.1, 0.5]
    kp2[:, 1, 0] = [0.5, 0.1, 0.5, 0.1]
    assert metrics.semantic_consistency(kp2, gt2) == pytest.approx(0.5)
    acc = metrics.SemanticConsistency()
    acc.update(kp2[:2], gt2[:2])
    acc.update(kp2[2:], gt2[2:])
    assert acc.result() == pytest.approx(0.5)
    np.testing.assert_allclose(acc.per_joint(), [0.5])


def test_semantic_consistency_published_definition_drops_faint_keypoints_per_frame():
    # One joint at the origin, two keypoints over 3 frames. Keypoint 0 sits on the joint but its
    # alpha is 0.1 in frame 1 (below 0.2): there it is no candidate, keypoint 1 (at x=0.9) is
    # the nearest. Counts: joint 0 -> keypoint 0 in frames 0 and 2, keypoint 1 in frame 1, so
    # p(0) = 2/3, p(1) = 1/3 and SC = max = 2/3.
    gt = np.zeros((3, 1, 3), np.float32)
    kp = np.array([[[0.0, 0, 0, 1.0], [0.9, 0, 0, 1.0]]] * 3, np.float32)
    kp[1, 0, 3] = 0.1
    counts, frames = metrics.nearest_keypoint_counts(jnp.asarray(kp), jnp.asarray(gt))
    np.testing.assert_allclose(counts, [[2, 1]])
    assert float(frames) == 3
    assert metrics.semantic_consistency(kp, gt) == pytest.approx(2 / 3)
    # The fixed node set (mean alpha 0.7 >= 0.2) keeps keypoint 0 a candidate in every frame.
    assert metrics.semantic_consistency(kp, gt, nodes="fixed") == pytest.approx(1.0)
    acc = metrics.SemanticConsistency()
    acc.update(kp[:1], gt[:1])
    acc.update(kp[1:], gt[1:])
    assert acc.scores() == pytest.approx({"sc": 2 / 3, "sc_fixed_nodes": 1.0})
    np.testing.assert_allclose(acc.per_joint(), [2 / 3])
    # A frame where no keypoint reaches 0.2 counts as a frame, for no keypoint: p(0) = 2/4.
    none = np.concatenate([kp, kp[:1] * np.array([1, 1, 1, 0.1], np.float32)])
    gt4 = np.zeros((4, 1, 3), np.float32)
    np.testing.assert_allclose(metrics.nearest_keypoint_counts(none, gt4)[0], [[2, 1]])
    assert metrics.semantic_consistency(none, gt4) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="SC nodes"):
        metrics.semantic_consistency(kp, gt, nodes="mean")


def test_semantic_consistency_fixed_nodes_by_mean_intensity():
    gt = np.zeros((3, 1, 3), np.float32)
    kp = np.array([[[0.0, 0, 0, 0.1], [0.9, 0, 0, 1.0]]] * 3, np.float32)
    counts, _ = metrics.nearest_keypoint_counts(jnp.asarray(kp), jnp.asarray(gt), 0.2, "fixed")
    np.testing.assert_allclose(counts, [[0, 3]])  # the closer keypoint is too faint
    # A node whose alpha flickers around the threshold (mean 0.3) stays a node in every frame
    # of the fixed set, so the joint keeps the same nearest keypoint; per frame it does not.
    flicker = kp.copy()
    flicker[:, 0, 3] = [0.15, 0.6, 0.15]
    np.testing.assert_array_equal(metrics.skeleton_nodes(jnp.asarray(flicker)), [True, True])
    assert metrics.semantic_consistency(flicker, gt, nodes="fixed") == pytest.approx(1.0)
    assert metrics.semantic_consistency(flicker, gt) == pytest.approx(2 / 3)
    # With every keypoint faint, the brightest one is still a node.
    faint = kp * np.array([1, 1, 1, 0.1], np.float32)
    np.testing.assert_array_equal(metrics.skeleton_nodes(jnp.asarray(faint)), [False, True])
    with pytest.raises(ValueError, match="same"):
        metrics.semantic_consistency(kp, np.zeros((2, 1, 3)))
    acc = metrics.SemanticConsistency()
    acc.update(kp[:, :1], gt)
    with pytest.raises(ValueError, match="changed"):
        acc.update(kp, gt)


def test_bone_length_variation_hand_cases():
    # A 3-keypoint chain 0 <- 1 <- 2 over 2 frames. Bone (1, 0) keeps length 1; bone (2, 1) has
    # lengths 1 and 3: mean 2, std 1, ratio 1/2. Mean over the two bones: 0.25.
    kp = np.zeros((2, 3, 4), np.float32)
    kp[..., 3] = 1.0
    kp[:, 1, 0] = 1.0
    kp[0, 2, 0], kp[1, 2, 0] = 2.0, 4.0
    parents = np.array([0, 0, 1])
    np.testing.assert_allclose(
        metrics.bone_lengths(jnp.asarray(kp), parents), [[0, 1, 1], [0, 1, 3]]
    )
    assert float(metrics.bone_length_variation(kp, parents)) == pytest.approx(0.25)
    # Averaged over sequences too: with a rigid second sequence, 0.125.
    rigid = kp.copy()
    rigid[1, 2, 0] = 2.0
    both = np.stack([kp, rigid])
    assert float(metrics.bone_length_variation(both, parents)) == pytest.approx(0.125)
    # A keypoint whose mean alpha is below 0.2 is not a node: its bone does not count.
    faint = kp.copy()
    faint[:, 2, 3] = 0.1
    assert float(metrics.bone_length_variation(faint, parents)) == pytest.approx(0.0)
    # Only the root kept: no bone, nan.
    faint[:, 1, 3] = 0.1
    assert np.isnan(float(metrics.bone_length_variation(faint, parents)))
    # A given node set replaces the intensity threshold: all three kept, as in the first case.
    kept = np.ones(3, bool)
    assert float(metrics.bone_length_variation(faint, parents, kept=kept)) == pytest.approx(0.25)
    # Rigid motion of the whole body (rotation + translation per frame) scores 0.
    rng = np.random.default_rng(0)
    rest = rng.normal(size=(5, 3))
    frames = []
    for _ in range(6):
        q, _r = np.linalg.qr(rng.normal(size=(3, 3)))
        frames.append(rest @ q.T + rng.normal(size=3))
    moving = np.concatenate([np.stack(frames), np.ones((6, 5, 1))], -1).astype(np.float32)
    jitted = jax.jit(metrics.bone_length_variation)
    assert float(jitted(moving, np.array([0, 0, 1, 1, 3]))) == pytest.approx(0.0, abs=1e-5)
    with pytest.raises(ValueError, match="T >= 2"):
        metrics.bone_length_variation(kp[:1], parents)
    with pytest.raises(ValueError, match="parents"):
        metrics.bone_length_variation(kp, np.array([0, 0]))


@SETTINGS
@given(
    n=st.sampled_from([1, 13, 40]),
    m=st.sampled_from([2, 29]),
    chunk=st.sampled_from([4, 2048]),
    seed=st.integers(0, 99),
)
def test_chamfer_matches_numpy(n, m, chunk, seed):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, 3)).astype(np.float32)
    b = rng.normal(size=(m, 3)).astype(np.float32)
    got = _chamfer_jit(jnp.asarray(a), jnp.asarray(b), chunk=chunk)
    np.testing.assert_allclose(got, np_chamfer(a, b), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(metrics.point_chamfer(a, b), np_chamfer(a, b), rtol=1e-4, atol=1e-5)


def test_chamfer_masks_empty_and_jit():
    a = jnp.array([[0.0, 0, 0], [1, 0, 0], [9, 9, 9]])
    b = jnp.array([[0.0, 0, 1], [5, 5, 5]])
    am, bm = jnp.array([True, True, False]), jnp.array([True, False])
    # a' = {0, e_x}, b' = {e_z}: a->b: (1 + 2) / 2; b->a: 1.
    f = jax.jit(metrics.chamfer_distance)
    np.testing.assert_allclose(f(a, b, am, bm), 2.5, rtol=1e-6)
    np.testing.assert_allclose(metrics.chamfer_distance(a, a), 0.0, atol=1e-6)
    none = jnp.zeros(3, bool)
    assert float(metrics.chamfer_distance(a, b, none, jnp.zeros(2, bool))) == 0.0
    assert np.isnan(float(metrics.chamfer_distance(a, b, none, bm)))
    assert float(metrics.chamfer_distance(a, b, none, bm, empty_value=12.0)) == 12.0
    assert float(metrics.chamfer_distance(jnp.zeros((0, 3)), jnp.zeros((0, 3)))) == 0.0


def test_tracking_chamfer():
    g = 6
    x = np.linspace(-1, 1, g)
    v = np.zeros((2, g, g, g), np.float32)
    v[:, 1, 1, 1] = 1
    r = np.zeros_like(v)
    r[0, 1, 1, 1] = 0.9  # exact after thresholding
    r[1, 1, 1, 2] = 0.6  # one cell off: CD = 2 * (cell)^2
    r[1, 4, 4, 4] = 0.4  # below threshold: ignored
    cell = x[1] - x[0]
    want = (0 + 2 * cell**2) / 2 * 1e4
    assert metrics.tracking_chamfer(v, r) == pytest.approx(want, rel=1e-4)
    # An empty reconstruction scores the worst value, not a skipped frame.
    assert metrics.tracking_chamfer(v[:1], np.zeros_like(v[:1]), scale=1.0) == pytest.approx(12.0)
    with pytest.raises(ValueError, match="equal shape"):
        metrics.tracking_chamfer(v, r[:1])


def test_motion_chamfer():
    g = 8
    x = np.linspace(-1, 1, g)
    v = np.zeros((3, g, g, g), np.float32)
    v[0, 2, 2, 2] = v[1, 3, 2, 2] = v[2, 4, 2, 2] = 1  # a cell moving along x
    assert metrics.motion_chamfer(v, v) == pytest.approx(0.0)
    # A reconstruction whose moving cell is shifted by one cell in y.
    r = np.zeros_like(v)
    r[0, 2, 3, 2] = r[1, 3, 3, 2] = r[2, 4, 3, 2] = 0.8
    cell2 = (x[1] - x[0]) ** 2
    # Each frame: V+ vs V-hat+ off by one cell (2 cell^2), same for V-; mean over 2 steps.
    assert metrics.motion_chamfer(v, r) == pytest.approx(4 * cell2, rel=1e-4)
    # Static reconstruction: every difference set empty on one side -> worst value per term.
    static = np.repeat(v[:1], 3, axis=0)
    assert metrics.motion_chamfer(v, static) == pytest.approx(2 * 12.0)
    with pytest.raises(ValueError, match="2 frames"):
        metrics.motion_chamfer(v[:1], v[:1])


# --- generated motion ---------------------------------------------------------------------------


def clips_at(offsets: np.ndarray, t: int = 4, k: int = 3) -> np.ndarray:
    """(len(offsets), t, k, 4) clips of one random body, each shifted along x by its offset;
    random intensities (the measures ignore alpha)."""
    rng = np.random.default_rng(0)
    body = rng.normal(size=(t, k, 3))
    clips = body[None] + np.asarray(offsets, np.float64)[:, None, None, None] * np.eye(3)[0]
    alpha = rng.uniform(size=(len(offsets), t, k, 1))
    return np.concatenate([clips, alpha], axis=-1).astype(np.float32)


def test_keypoint_distance_is_the_mean_euclidean_xyz_distance():
    a = np.zeros((2, 2, 4), np.float32)  # (T, K, 4)
    b = a.copy()
    b[:, 0, :3] = (3.0, 4.0, 0.0)  # keypoint 0 is 5 away in every frame, keypoint 1 0
    b[..., 3] = 1.0  # alpha differs and does not count
    assert float(metrics.keypoint_distance(a, b)) == pytest.approx(2.5)
    assert float(metrics.keypoint_distance(a, b, np.array([True, False]))) == pytest.approx(5.0)
    assert float(metrics.keypoint_distance(a, a)) == 0.0
    with pytest.raises(ValueError, match=r"mask has shape \(3,\).*K=2"):
        metrics.keypoint_distance(a, b, np.ones(3, bool))


def test_diversity_hand_cases():
    # Three samples shifted by 0, 1 and 3 along x: pairwise distances 1, 3, 2; mean 2.
    samples = clips_at([0.0, 1.0, 3.0])
    assert float(metrics.diversity(samples)) == pytest.approx(2.0, rel=1e-5)
    # Identical samples: exactly 0, with a finite gradient.
    same = clips_at([0.5, 0.5, 0.5])
    assert float(metrics.diversity(same)) == 0.0
    grad = jax.grad(lambda x: metrics.diversity(x))(jnp.asarray(same))
    assert np.all(np.isfinite(np.asarray(grad)))
    # One value per conditioning clip, under jit.
    batch = np.stack([samples, same, clips_at([0.0, 2.0, 2.0])])  # (B=3, S=3, T, K, 4)
    out = jax.jit(metrics.diversity)(batch)
    assert out.shape == (3,)
    np.testing.assert_allclose(out, [2.0, 0.0, 4.0 / 3.0], rtol=1e-5)
    with pytest.raises(ValueError, match="S >= 2"):
        metrics.diversity(samples[:1])
    with pytest.raises(ValueError, match="S >= 2"):
        metrics.diversity(samples[0])  # (T, K, 4): not a set of samples


def test_set_diversity_splits_the_diversity_of_the_whole_set_by_clip():
    clips = np.stack([clips_at([0.0, 1.0]), clips_at([3.0, 7.0]), clips_at([2.0, 2.0])])
    per_clip = np.asarray(metrics.set_diversity(clips))
    assert per_clip.shape == (3,)
    whole = float(metrics.diversity(clips.reshape(6, *clips.shape[2:])))
    assert float(np.mean(per_clip)) == pytest.approx(whole, rel=1e-5)
    # Clip 0's samples at x = 0, 1 are 1, 3, 7, 2, 2 and 1, 2, 6, 1, 1 away from the others.
    assert per_clip[0] == pytest.approx((15 + 11) / 10, rel=1e-5)
    # Every clip the same pose: no spread.
    assert np.all(np.asarray(metrics.set_diversity(np.stack([clips_at([1.0, 1.0])] * 2))) == 0)
    with pytest.raises(ValueError, match=r"\(B, S, T, K, C\)"):
        metrics.set_diversity(clips[0])


def test_set_distance_hand_cases():
    rng = np.random.default_rng(1)
    real = rng.normal(size=(5, 6, 4, 4)).astype(np.float32)  # (M, T, K, 4)
    root = 2
    # The same set, in another order and with every clip's root translated frame by frame:
    # the root translation is removed, so the distance is 0.
    moved = real[::-1].copy()
    moved[..., :3] += rng.normal(size=(5, 6, 1, 3)).astype(np.float32)
    assert float(metrics.set_distance(moved, real, root)) == pytest.approx(0.0, abs=1e-6)
    assert float(metrics.set_distance(moved, real, None)) > 0.1  # absolute positions differ
    # Generated {A, A'} with A' = A moved 0.5 along x on every keypoint but the root (3 of 4
    # keypoints): A' is 0.375 from its nearest real clip A, A is 0 from itself.
    a = real[:1]
    a_far = a.copy()
    a_far[:, :, [0, 1, 3], 0] += 0.5
    to_real, to_generated = metrics.nearest_clip_distances(np.concatenate([a, a_far]), a, root)
    np.testing.assert_allclose(to_real, [0.0, 0.375], atol=1e-6)
    np.testing.assert_allclose(to_generated, [0.0], atol=1e-6)
    assert float(metrics.set_distance(np.concatenate([a, a_far]), a, root)) == pytest.approx(
        0.1875, abs=1e-6
    )
    # Coverage: a generated set of one real clip is far from the four others.
    assert float(metrics.set_distance(real[:1], real, root)) > 0.5
    jitted = jax.jit(metrics.set_distance, static_argnames="root")
    assert float(jitted(real, real, root=root)) == 0.0
    # Shapes of the pairwise matrix, and bad inputs.
    d = metrics.clip_distances(real[:2], real)
    assert d.shape == (2, 5)
    assert float(d[1, 3]) == pytest.approx(float(metrics.keypoint_distance(real[1], real[3])))
    with pytest.raises(ValueError, match="same number of frames"):
        metrics.set_distance(real[:, :5], real, root)
    with pytest.raises(ValueError, match="empty"):
        metrics.set_distance(real[:0], real, root)
    with pytest.raises(ValueError, match=r"\(N, T, K, C\)"):
        metrics.set_distance(real[0], real, root)


# --- skeleton against the ground truth ----------------------------------------------------------

CHAIN = np.array([0, 0, 1])  # the true tree of a three-joint chain 0 - 1 - 2


def chain_frames(frames: int = 3) -> np.ndarray:
    """(F, 3, 3) joints of a straight chain 0.3 apart along x, translated frame by frame."""
    rest = np.array([[0.0, 0, 0], [0.3, 0, 0], [0.6, 0, 0]])
    shift = np.linspace(-0.2, 0.2, frames)[:, None, None] * np.array([1.0, 0.5, -0.3])
    return (rest + shift).astype(np.float32)


def with_alpha(positions: np.ndarray) -> np.ndarray:
    return np.concatenate([positions, np.ones((*positions.shape[:-1], 1), np.float32)], -1)


def test_keypoints_on_the_joints_of_a_chain_score_one_everywhere():
    gt = chain_frames()
    kp = with_alpha(gt)  # keypoint k sits on joint k in every frame
    kept = np.ones(3, bool)
    scores = metrics.skeleton_agreement(kp, gt, kept, CHAIN, CHAIN)
    assert scores == pytest.approx(
        {
            "joint_distance": 0.0,
            "joint_coverage_0.05": 1.0,
            "joint_coverage_0.10": 1.0,
            "edge_precision": 1.0,
            "edge_precision_within_2_hops": 1.0,
            "bone_recall": 1.0,
            "distinct_nodes": 3,
        }
    )
    assert isinstance(scores["distinct_nodes"], int)
    assert metrics.semantic_consistency(kp, gt) == pytest.approx(1.0)
    np.testing.assert_array_equal(metrics.joint_nodes(kp, gt, kept), [0, 1, 2])
    np.testing.assert_array_equal(metrics.node_joints(kp, gt), [0, 1, 2])
    # Without the trees only the tree-blind measures are reported.
    assert set(metrics.skeleton_agreement(kp, gt, kept)) == {
        "joint_distance",
        "joint_coverage_0.05",
        "joint_coverage_0.10",
        "distinct_nodes",
    }


def test_a_skeleton_linking_the_two_ends_of_a_chain_loses_precision():
    gt = chain_frames()
    kp, kept = with_alpha(gt), np.ones(3, bool)
    # Skeleton edges 1 - 0 (a true bone) and 2 - 0 (joints two hops apart in the true chain):
    # precision 1/2, within two hops 1. True bones 1 - 0 (adjacent in the skeleton) and 2 - 1
    # (two hops apart in it): recall 1/2. Where the nodes are is unchanged.
    ends = np.array([0, 0, 0])
    scores = metrics.skeleton_agreement(kp, gt, kept, ends, CHAIN)
    assert scores["edge_precision"] == pytest.approx(0.5)
    assert scores["edge_precision_within_2_hops"] == pytest.approx(1.0)
    assert scores["bone_recall"] == pytest.approx(0.5)
    assert scores["joint_distance"] == 0.0 and scores["distinct_nodes"] == 3
    # A four-joint chain whose skeleton links joint 0 to joint 3 (three hops): 2 of 3 edges are
    # right, with or without the second hop.
    chain4 = np.array([0, 0, 1, 2])
    gt4 = np.concatenate([gt, gt[:, 2:] + np.float32([0.3, 0, 0])], axis=1)
    link = np.array([0, 0, 1, 0])
    for hops in (1, 2):
        precision = metrics.edge_precision(
            with_alpha(gt4), gt4, np.ones(4, bool), link, chain4, hops
        )
        assert float(precision) == pytest.approx(2 / 3)
    # Only one kept node: no edge, nan precision; a one-joint tree: no bone, nan recall.
    lone = np.array([True, False, False])
    assert np.isnan(float(metrics.edge_precision(kp, gt, lone, CHAIN, CHAIN)))
    one = gt[:, :1]
    assert np.isnan(float(metrics.bone_recall(kp, one, kept, CHAIN, np.array([0]))))


def test_keypoints_bunched_at_one_joint_lose_coverage_and_distinct_nodes_but_keep_sc():
    gt = chain_frames()
    # All three keypoints within 0.04 of joint 0, moving with it: every joint keeps keypoint 0 as
    # its nearest in every frame, so SC is 1, yet only joint 0 is covered and one node is used.
    offsets = np.float32([[0, 0, 0], [0, 0.02, 0], [0, 0.04, 0]])
    kp = with_alpha(gt[:, :1] + offsets)
    kept = np.ones(3, bool)
    assert metrics.semantic_consistency(kp, gt) == pytest.approx(1.0)
    scores = metrics.skeleton_agreement(kp, gt, kept, CHAIN, CHAIN)
    assert scores["joint_distance"] == pytest.approx((0.0 + 0.3 + 0.6) / 3, abs=1e-6)
    assert scores["joint_coverage_0.05"] == pytest.approx(1 / 3)
    assert scores["joint_coverage_0.10"] == pytest.approx(1 / 3)
    assert scores["distinct_nodes"] == 1
    # Every joint maps onto the same node and every node onto joint 0: the tree measures see no
    # wrong edge or missing bone, which is why coverage and distinct nodes stand beside them.
    assert scores["bone_recall"] == 1.0 and scores["edge_precision"] == 1.0
    # Coverage by radius: joint 1 lies 0.3 from the bunch.
    cover = metrics.joint_coverage(kp, gt, kept, 0.3001)
    assert float(cover) == pytest.approx(2 / 3)


def test_only_kept_nodes_count():
    gt = chain_frames()
    kp = with_alpha(gt)
    keep = np.array([True, True, False])  # keypoint 2, on joint 2, is pruned
    scores = metrics.skeleton_agreement(kp, gt, keep, CHAIN, CHAIN)
    # Joint 2's nearest kept node is keypoint 1, 0.3 away.
    assert scores["joint_distance"] == pytest.approx(0.1, abs=1e-6)
    assert scores["joint_coverage_0.10"] == pytest.approx(2 / 3)
    assert scores["distinct_nodes"] == 2
    # One edge between kept nodes (1 - 0, right); bone 2 - 1 maps onto node 1 alone: recalled.
    assert scores["edge_precision"] == 1.0 and scores["bone_recall"] == 1.0
    np.testing.assert_array_equal(metrics.joint_nodes(kp, gt, keep), [0, 1, 1])
    with pytest.raises(ValueError, match="kept nodes"):
        metrics.joint_distance(kp, gt, keep[:2])
    with pytest.raises(ValueError, match="same frames"):
        metrics.joint_distance(kp[:2], gt, keep)
    with pytest.raises(ValueError, match="true parents"):
        metrics.skeleton_agreement(kp, gt, keep, CHAIN, np.array([0, 0]))


def test_most_frequent_node_and_its_tie_break():
    # Joint 0 at the origin; keypoint 0 at x = 0.1 in frames 0-1 and 0.5 in frames 2-3, keypoint
    # 1 the other way round but at 0.2: each is nearest in two frames, and the tie goes to the
    # smaller mean distance, keypoint 0 (0.3 against 0.35), whatever the keypoint order.
    gt = np.zeros((4, 1, 3), np.float32)
    kp = np.zeros((4, 2, 4), np.float32)
    kp[:, 0, 0] = [0.1, 0.1, 0.5, 0.5]
    kp[:, 1, 0] = [0.6, 0.6, 0.2, 0.2]
    kept = np.ones(2, bool)
    assert int(metrics.joint_nodes(kp, gt, kept)[0]) == 0
    assert int(metrics.joint_nodes(kp[:, ::-1], gt, kept)[0]) == 1


def test_tree_within_counts_hops():
    chain4 = np.array([0, 0, 1, 2])
    hops = np.abs(np.arange(4)[:, None] - np.arange(4)[None])  # hop distance along the chain
    for h in (0, 1, 2, 3):
        np.testing.assert_array_equal(metrics.tree_within(chain4, h), hops <= h)
    star = np.array([0, 0, 0, 0])
    within = np.asarray(metrics.tree_within(star, 1))
    assert within[0].all() and not within[1, 2] and metrics.tree_within(star, 2).all()


def test_skeleton_measures_under_jit_and_vmap():
    rng = np.random.default_rng(3)
    gt = rng.uniform(-1, 1, (3, 4, 5, 3)).astype(np.float32)  # (sequences, F, J, 3)
    kp = rng.uniform(-1, 1, (3, 4, 6, 4)).astype(np.float32)
    kept = np.array([True, True, False, True, True, True])
    parents, true_parents = np.array([0, 0, 1, 1, 3, 4]), np.array([0, 0, 1, 2, 0])
    per_sequence = jax.vmap(metrics.joint_distance, in_axes=(0, 0, None))(kp, gt, kept)
    expected = [float(metrics.joint_distance(kp[s], gt[s], kept)) for s in range(3)]
    np.testing.assert_allclose(per_sequence, expected, rtol=1e-6)
    d = np.linalg.norm(gt[:, :, :, None] - kp[:, :, None, :, :3], axis=-1)[..., kept]
    assert float(metrics.joint_distance(kp, gt, kept)) == pytest.approx(d.min(-1).mean(), 1e-6)
    jitted = jax.jit(metrics.edge_precision, static_argnames="hops")
    for hops in (1, 2):
        assert float(jitted(kp, gt, kept, parents, true_parents, hops=hops)) == pytest.approx(
            float(metrics.edge_precision(kp, gt, kept, parents, true_parents, hops))
        )
    coverage = jax.jit(metrics.joint_coverage)(kp, gt, kept, 0.5)
    assert float(coverage) == pytest.approx(np.mean(d.min(-1) <= 0.5))
    recall = jax.jit(metrics.bone_recall)(kp, gt, kept, parents, true_parents)
    assert 0.0 <= float(recall) <= 1.0
    assert 1 <= int(jax.jit(metrics.distinct_nodes)(kp, gt, kept)) <= 5


def random_tree(rng: np.random.Generator, n: int) -> np.ndarray:
    """Parents of a random tree over n vertices, rooted at a random vertex."""
    order = rng.permutation(n)
    parents = np.empty(n, int)
    parents[order[0]] = order[0]
    for i in range(1, n):
        parents[order[i]] = order[rng.integers(0, i)]
    return parents


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), perm=st.permutations(range(6)))
def test_skeleton_measures_do_not_depend_on_the_keypoint_order(seed, perm):
    rng = np.random.default_rng(seed)
    gt = rng.uniform(-1, 1, (4, 5, 3)).astype(np.float32)  # F = 4 frames, J = 5 joints
    kp = rng.uniform(-1, 1, (4, 6, 4)).astype(np.float32)  # K = 6 keypoints
    kept = rng.random(6) < 0.7
    kept[rng.integers(6)] = True
    parents, true_parents = random_tree(rng, 6), random_tree(rng, 5)
    scores = metrics.skeleton_agreement(kp, gt, kept, parents, true_parents)
    # Keypoint i of the permuted set is keypoint perm[i]; its parent is renamed the same way.
    perm = np.asarray(perm)
    rename = np.argsort(perm)
    permuted = metrics.skeleton_agreement(
        kp[:, perm], gt, kept[perm], rename[parents[perm]], true_parents
    )
    assert permuted == pytest.approx(scores, rel=1e-6, nan_ok=True)
