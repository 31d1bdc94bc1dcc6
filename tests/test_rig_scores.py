"""The field's scores of a rig (`nmjax.metrics.rig_scores`): tree edit distance, CD-J2J / J2B /
B2B and the rig's fit error, on hand-computed cases and properties."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nmjax import metrics
from nmjax.geometry import linear_blend_skinning

SETTINGS = settings(max_examples=25, deadline=None)

# --- tree edit distance ------------------------------------------------------------------------

ARM = np.array([0, 0, 1, 2, 1, 4])  # root 0; chains 0-1-2-3 and 1-4-5


def test_a_tree_is_at_distance_zero_from_itself_and_from_a_renumbering():
    assert metrics.tree_edit_distance(ARM, ARM) == 0
    # The same tree with its nodes numbered backwards: node k becomes 5 - k.
    rename = 5 - np.arange(6)
    renumbered = np.empty(6, int)
    renumbered[rename] = rename[ARM]
    assert renumbered.tolist() == [1, 4, 3, 4, 5, 5]
    assert metrics.tree_edit_distance(ARM, renumbered) == 0


def test_moving_one_leaf_to_another_parent_costs_one_delete_and_one_insert():
    # Leaf 3 moves from node 2 to the root: [0, 0, 1, 0, 1, 4]. Both trees have 6 nodes, so an
    # edit script deletes as many nodes as it inserts, d of each at cost 2d (renaming is free).
    # The shapes differ (ARM's root has one child, the new root two), so d >= 1; deleting leaf 3
    # and inserting it under the root is d = 1: the distance is 2.
    moved = ARM.copy()
    moved[3] = 0
    assert metrics.tree_edit_distance(ARM, moved) == 2
    assert metrics.tree_edit_distance(moved, ARM) == 2
    # The chain 0-1-2 with a leaf 3 on the root, against the chain 0-1-2-3 (leaf 3 moved under
    # 2): four nodes each, different shapes, one delete and one insert: 2.
    assert metrics.tree_edit_distance([0, 0, 1, 0], [0, 0, 1, 2]) == 2
    # Moving a leaf between two nodes of the same shape gives the same unlabelled tree: 0.
    assert metrics.tree_edit_distance([0, 0, 0, 1], [0, 0, 0, 2]) == 0


def test_the_kept_mask_prunes_to_the_nearest_kept_ancestor():
    # Keeping 0, 1 and 2 of ARM leaves the chain 0-1-2: three deletions from the full tree.
    keep = np.array([True, True, True, False, False, False])
    assert metrics.tree_edit_distance(ARM, ARM, keep) == 3
    assert metrics.tree_edit_distance(ARM, [0, 0, 1], keep) == 0
    # Dropping node 1 hangs 2 and 4 off the root: a root with chains 2-3 and 4-5.
    skip = np.array([True, False, True, True, True, True])
    assert metrics.tree_edit_distance(ARM, [0, 0, 1, 0, 3], skip) == 0
    with pytest.raises(ValueError, match="drops the root"):
        metrics.tree_edit_distance(ARM, ARM, ~keep)
    with pytest.raises(ValueError, match="kept mask"):
        metrics.tree_edit_distance(ARM, ARM, keep[:3])
    with pytest.raises(ValueError, match="exactly one root"):
        metrics.tree_edit_distance([1, 0, 1], ARM)
    with pytest.raises(ValueError, match="never reach the root"):
        metrics.tree_edit_distance([0, 2, 1], ARM)


@st.composite
def trees(draw, max_nodes: int = 9):
    """A random tree's parents, its nodes numbered at random (root its own parent)."""
    n = draw(st.integers(1, max_nodes))
    attach = [draw(st.integers(0, k - 1)) for k in range(1, n)]  # node k hangs off node < k
    rename = np.asarray(draw(st.permutations(range(n))))
    parents = np.empty(n, int)
    parents[rename[0]] = rename[0]
    for k, p in enumerate(attach, start=1):
        parents[rename[k]] = rename[p]
    return parents


@SETTINGS
@given(a=trees(), b=trees(), c=trees(), perm=st.permutations(range(9)))
def test_tree_edit_distance_is_a_metric_bounded_by_the_node_counts(a, b, c, perm):
    ab = metrics.tree_edit_distance(a, b)
    assert ab == metrics.tree_edit_distance(b, a)
    assert metrics.tree_edit_distance(a, a) == 0
    # At least the difference in size (every extra node is deleted or inserted), at most
    # deleting all of A but the root and inserting all of B but the root.
    assert abs(len(a) - len(b)) <= ab <= len(a) + len(b) - 2
    assert metrics.tree_edit_distance(a, c) <= ab + metrics.tree_edit_distance(b, c)
    # Renumbering the nodes changes nothing.
    rename = np.array([p for p in perm if p < len(a)])
    renumbered = np.empty_like(a)
    renumbered[rename] = rename[a]
    assert metrics.tree_edit_distance(renumbered, b) == ab


# --- CD-J2J, CD-J2B, CD-B2B --------------------------------------------------------------------

# Skeleton A: root at the origin, a bone of length 2 along x and one of length 1 along z.
A_JOINTS = np.float32([[0, 0, 0], [2, 0, 0], [0, 0, 1]])
A_PARENTS = np.array([0, 0, 0])
# Skeleton B: the root and A's x bone only.
B_JOINTS = np.float32([[0, 0, 0], [2, 0, 0]])
B_PARENTS = np.array([0, 0])


def test_a_skeleton_against_itself_scores_zero():
    rng = np.random.default_rng(0)
    joints = rng.uniform(-0.5, 0.5, (4, 6, 3)).astype(np.float32)  # 4 frames, 6 joints
    for cd in (metrics.cd_j2j(joints, joints), metrics.cd_j2b(joints, ARM, joints, ARM)):
        np.testing.assert_allclose(cd, 0.0, atol=1e-6)
    np.testing.assert_allclose(metrics.cd_b2b(joints, ARM, joints, ARM), 0.0, atol=1e-6)
    scores = metrics.skeleton_chamfers(joints, ARM, joints, ARM, joints)
    assert set(scores) == {"cd_j2j", "cd_j2b", "cd_b2b"}
    for value in scores.values():
        assert value.shape == (4,)
        np.testing.assert_allclose(value, 0.0, atol=1e-4)


def test_cd_j2j_hand_case():
    # A's joints to B's nearest: 0, 0 and 1 (the z tip is 1 from the root): mean 1/3. B's to
    # A's: 0, 0. CD-J2J = (1/3 + 0) / 2.
    assert float(metrics.cd_j2j(A_JOINTS, B_JOINTS)) == pytest.approx(1 / 6, rel=1e-6)
    # Masking A's z tip leaves the same joints on both sides.
    mask = np.array([True, True, False])
    assert float(metrics.cd_j2j(A_JOINTS, B_JOINTS, mask)) == pytest.approx(0.0, abs=1e-7)
    assert np.isnan(float(metrics.cd_j2j(A_JOINTS, B_JOINTS, np.zeros(3, bool))))


def test_cd_j2b_hand_cases():
    # Every joint of B lies on A's x bone; of A's joints only the z tip is off B's bone, by 1:
    # (1/3 + 0) / 2, as CD-J2J, since B's one bone runs between its joints.
    assert float(metrics.cd_j2b(A_JOINTS, A_PARENTS, B_JOINTS, B_PARENTS)) == pytest.approx(1 / 6)
    # A joint near the middle of a bone is measured to the bone, not to its ends: a horizontal
    # bone (0, 0, 0)-(2, 0, 0) against a vertical one (1, 1, 0)-(1, 3, 0). The horizontal
    # bone's ends are sqrt(2) from (1, 1, 0), the nearest point of the vertical bone; the
    # vertical bone's ends are 1 and 3 above the horizontal one: (sqrt(2) + 2) / 2.
    vertical = np.float32([[1, 1, 0], [1, 3, 0]])
    got = float(metrics.cd_j2b(B_JOINTS, B_PARENTS, vertical, B_PARENTS))
    assert got == pytest.approx((np.sqrt(2) + 2) / 2, rel=1e-6)
    # A skeleton with no bone (only its root kept) has no joint-to-bone distance.
    root_only = np.array([True, False, False])
    assert np.isnan(float(metrics.cd_j2b(A_JOINTS, A_PARENTS, B_JOINTS, B_PARENTS, root_only)))


def test_cd_b2b_hand_cases():
    # A's bones against B's: the x bone (length 2) lies on B's bone, distance 0 all along; a
    # point z up A's z bone (length 1) is z from B's bone, mean 1/2 along it. By length:
    # (2 * 0 + 1 * 1/2) / 3 = 1/6 (weighting the two bones alike would give 1/4). B's bone lies
    # on A's: 0. CD-B2B = (1/6 + 0) / 2. The midpoint samples of a linear distance are exact.
    got = float(metrics.cd_b2b(A_JOINTS, A_PARENTS, B_JOINTS, B_PARENTS))
    assert got == pytest.approx(1 / 12, rel=1e-5)
    # Two perpendicular unit bones meeting at the origin: a point x along one is x from the
    # other, mean 1/2 each way: CD-B2B = 1/2.
    x_bone = np.float32([[0, 0, 0], [1, 0, 0]])
    y_bone = np.float32([[0, 0, 0], [0, 1, 0]])
    assert float(metrics.cd_b2b(x_bone, B_PARENTS, y_bone, B_PARENTS)) == pytest.approx(0.5)
    # Two parallel bones 1 apart: 1 everywhere.
    raised = x_bone + np.float32([0, 0, 1])
    assert float(metrics.cd_b2b(x_bone, B_PARENTS, raised, B_PARENTS)) == pytest.approx(1.0)


def test_skeleton_chamfers_place_both_skeletons_in_the_true_body_box_and_scale_by_100():
    # The body spans 4 along x (and less along y, z), so every distance is divided by 4 + 1e-5.
    body = np.float32([[-1, 0, 0], [3, 1, 0.5]])
    scores = metrics.skeleton_chamfers(A_JOINTS, A_PARENTS, B_JOINTS, B_PARENTS, body)
    side = 4 + 1e-5
    assert float(scores["cd_j2j"]) == pytest.approx(100 / 6 / side, rel=1e-5)
    assert float(scores["cd_j2b"]) == pytest.approx(100 / 6 / side, rel=1e-5)
    assert float(scores["cd_b2b"]) == pytest.approx(100 / 12 / side, rel=1e-5)
    np.testing.assert_allclose(
        metrics.unit_box(body, body), [[-0.5, -0.125, -0.0625], [0.5, 0.125, 0.0625]], atol=1e-5
    )
    # Without the true tree only CD-J2J, which needs no bones.
    assert set(metrics.skeleton_chamfers(A_JOINTS, A_PARENTS, B_JOINTS, None, body)) == {"cd_j2j"}


def test_skeleton_chamfers_under_jit_and_vmap_match_frame_by_frame():
    rng = np.random.default_rng(1)
    joints = rng.uniform(-1, 1, (5, 6, 3)).astype(np.float32)  # 5 frames
    truth = rng.uniform(-1, 1, (5, 4, 3)).astype(np.float32)
    body = rng.uniform(-1, 1, (5, 50, 3)).astype(np.float32)
    true_parents, kept = np.array([0, 0, 1, 1]), np.array([True, True, True, False, True, True])

    def scores(j, t, b):
        return metrics.skeleton_chamfers(j, ARM, t, true_parents, b, kept)

    batched = jax.jit(scores)(joints, truth, body)
    mapped = jax.vmap(scores)(joints, truth, body)
    for key in ("cd_j2j", "cd_j2b", "cd_b2b"):
        one_by_one = [float(scores(joints[t], truth[t], body[t])[key]) for t in range(5)]
        np.testing.assert_allclose(batched[key], one_by_one, rtol=1e-5)
        np.testing.assert_allclose(mapped[key], one_by_one, rtol=1e-5)
    # Gradients are finite, also where a joint sits on a bone's end.
    grad = jax.grad(lambda j: metrics.cd_b2b(j, A_PARENTS, jnp.asarray(B_JOINTS), B_PARENTS))
    assert np.isfinite(np.asarray(grad(jnp.asarray(A_JOINTS)))).all()


# --- the rig's fit error -----------------------------------------------------------------------


def skinned_capture(rng: np.random.Generator, frames: int = 4) -> np.ndarray:
    """(T, V, 3): a random surface skinned by random weights and joint motions."""
    surface = rng.uniform(-0.8, 0.8, (60, 3)).astype(np.float32)
    weights = rng.dirichlet(np.ones(3), 60).astype(np.float32)
    rotations = np.stack(
        [np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(frames * 3)]
    ).reshape(frames, 3, 3, 3)
    rotations *= np.sign(np.linalg.det(rotations))[..., None, None]  # proper rotations
    translations = rng.normal(scale=0.1, size=(frames, 3, 3))
    return np.asarray(
        linear_blend_skinning(surface, weights, rotations=rotations, translations=translations)
    )


def test_the_fit_error_is_zero_when_the_frames_are_the_skinned_surface_and_grows_otherwise():
    rng = np.random.default_rng(2)
    skinned = skinned_capture(rng)
    fit = metrics.rig_fit_error(skinned, skinned, box_scale=4.0)
    # 0 up to float32 rounding of |a|^2 - 2 a.b + |b|^2 (about 1e-8 a term, 1e-4 x1e4).
    assert fit == pytest.approx({"cd": 0.0, "cd_capture": 0.0}, abs=1e-3)
    # The capture moved by d = 0.01 along x: every point's nearest neighbour is its own copy
    # (the points are further apart than 2d), so each direction contributes d^2: CD = 2d^2 in
    # every frame, x1e4 in the cube (2.0), / s^2 = / 16 in the capture's units.
    spread = np.linalg.norm(skinned[:, :, None] - skinned[:, None], axis=-1)
    assert np.sort(spread, axis=-1)[..., 1].min() > 0.02
    moved = skinned + np.float32([0.01, 0, 0])
    fit = metrics.rig_fit_error(skinned, moved, box_scale=4.0)
    assert fit["cd"] == pytest.approx(2e-4 * 1e4, rel=1e-3)
    assert fit["cd_capture"] == pytest.approx(2e-4 / 16, rel=1e-3)
    # A capture the rig does not follow scores more still.
    other = skinned_capture(np.random.default_rng(3))
    assert metrics.rig_fit_error(skinned, other, 4.0)["cd"] > 10 * fit["cd"]
    with pytest.raises(ValueError, match="same T"):
        metrics.rig_fit_error(skinned, skinned[:2], 4.0)
    with pytest.raises(ValueError, match="box_scale"):
        metrics.rig_fit_error(skinned, skinned, 0.0)
