import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads
from scipy.spatial.transform import Rotation

from nmjax import geometry as geo

SETTINGS = settings(max_examples=10, deadline=None)

# A small tree: 0 root; 1, 2 children of 0; 3 child of 1; 4 child of 3. Order is topological.
PARENTS = (0, 0, 0, 1, 3)
ORDER = (0, 2, 1, 3, 4)


def random_rotations(seed, n):
    return Rotation.random(n, random_state=seed).as_matrix().astype(np.float32)


@SETTINGS
@given(n=st.sampled_from([1, 6]), seed=st.integers(0, 999))
def test_6d_gives_rotations_and_round_trips(n, seed):
    d6 = np.random.default_rng(seed).normal(size=(2, n, 6)).astype(np.float32)
    rot = np.asarray(jax.jit(geo.rotation_6d_to_matrix)(d6))
    eye = np.broadcast_to(np.eye(3), rot.shape)
    np.testing.assert_allclose(np.swapaxes(rot, -1, -2) @ rot, eye, atol=1e-5)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-5)
    # First column is the normalised first half (the x axis).
    x = d6[..., :3] / np.linalg.norm(d6[..., :3], axis=-1, keepdims=True)
    np.testing.assert_allclose(rot[..., :, 0], x, atol=1e-5)
    back = geo.rotation_6d_to_matrix(geo.matrix_to_rotation_6d(jnp.asarray(rot)))
    np.testing.assert_allclose(back, rot, atol=1e-5)


def test_quaternion_conversions_match_scipy():
    rot = random_rotations(0, 64)
    # Include 180-degree rotations about each axis, where naive formulas break down.
    rot = np.concatenate([rot, np.diag([1.0, -1, -1])[None], np.diag([-1.0, 1, -1])[None]], 0)
    rot = rot.astype(np.float32)
    q = np.asarray(geo.matrix_to_quaternion(jnp.asarray(rot)))
    ref = Rotation.from_matrix(rot).as_quat()  # (x, y, z, w)
    ref = np.concatenate([ref[:, 3:], ref[:, :3]], -1)
    ref *= np.where(ref[:, :1] < 0, -1, 1)
    sign = np.sign(np.sum(q * ref, -1, keepdims=True))  # w = 0 leaves the sign free
    np.testing.assert_allclose(q, ref * sign, atol=1e-5)
    np.testing.assert_allclose(geo.quaternion_to_matrix(jnp.asarray(q)), rot, atol=1e-5)


def test_axis_angle_matches_scipy_and_zero():
    w = np.random.default_rng(1).normal(size=(10, 3)).astype(np.float32)
    ref = Rotation.from_rotvec(w).as_matrix()
    np.testing.assert_allclose(jax.jit(geo.axis_angle_to_matrix)(jnp.asarray(w)), ref, atol=1e-5)
    np.testing.assert_allclose(geo.axis_angle_to_matrix(jnp.zeros(3)), np.eye(3), atol=1e-7)
    g = jax.jit(jax.grad(lambda v: geo.axis_angle_to_matrix(v)[0, 1]))(jnp.zeros(3))
    np.testing.assert_allclose(g, [0, 0, -1], atol=1e-6)  # d R01 / d w_z = -1 at 0


def test_slerp_endpoints_norm_and_constant_speed():
    q = np.asarray(geo.matrix_to_quaternion(jnp.asarray(random_rotations(2, 8))))
    q0, q1 = jnp.asarray(q[:4]), jnp.asarray(q[4:])
    ts = jnp.linspace(0, 1, 5)
    path = jax.jit(jax.vmap(geo.slerp, in_axes=(None, None, 0)))(q0, q1, ts)  # (5, 4, 4)
    np.testing.assert_allclose(np.linalg.norm(path, axis=-1), 1.0, atol=1e-6)
    np.testing.assert_allclose(path[0], q0, atol=1e-6)
    sign = np.sign(np.sum(q[:4] * q[4:], -1, keepdims=True))
    np.testing.assert_allclose(path[-1], q[4:] * sign, atol=1e-5)
    # Constant angular speed: equal angles between consecutive samples.
    steps = np.arccos(np.clip(np.abs(np.sum(path[1:] * path[:-1], -1)), -1, 1))
    np.testing.assert_allclose(steps, steps[:1].repeat(4, 0), atol=1e-4)
    # Identical endpoints: the near-parallel branch, finite gradient.
    np.testing.assert_allclose(geo.slerp(q0, q0, 0.3), q0, atol=1e-6)
    g = jax.jit(jax.grad(lambda a: geo.slerp(a, q0, 0.3).sum()))(q0)
    assert np.all(np.isfinite(g))


def test_slerp_matrices_matches_scipy():
    r = random_rotations(3, 2)
    got = geo.slerp_matrices(jnp.asarray(r[0]), jnp.asarray(r[1]), 0.25)
    from scipy.spatial.transform import Slerp

    ref = Slerp([0, 1], Rotation.from_matrix(r))([0.25]).as_matrix()[0]
    np.testing.assert_allclose(got, ref, atol=1e-5)
    np.testing.assert_allclose(geo.slerp_matrices(r[0], r[1], 1.0), r[1], atol=1e-5)


def np_fk(root, local, offsets, parents, order):
    k = len(parents)
    glob = np.zeros((k, 3, 3))
    pos = np.zeros((k, 3))
    for j in order:
        if parents[j] == j:
            glob[j], pos[j] = local[j], root
        else:
            glob[j] = glob[parents[j]] @ local[j]
            pos[j] = pos[parents[j]] + glob[j] @ offsets[j]
    return pos, glob


def test_fk_identity_accumulates_offsets():
    offsets = np.arange(15, dtype=np.float32).reshape(5, 3)
    root = np.array([0.5, -1.0, 2.0], np.float32)
    pos = geo.forward_kinematics(
        root, jnp.broadcast_to(jnp.eye(3), (5, 3, 3)), offsets, PARENTS, ORDER
    )
    want = np.stack(
        [root, root + offsets[1], root + offsets[2], root + offsets[1] + offsets[3]]
        + [root + offsets[1] + offsets[3] + offsets[4]]
    )
    np.testing.assert_allclose(pos, want, rtol=1e-6)


@SETTINGS
@given(seed=st.integers(0, 999), batch=st.sampled_from([1, 3]))
def test_fk_matches_numpy_and_jit(seed, batch):
    rng = np.random.default_rng(seed)
    local = random_rotations(seed, batch * 5).reshape(batch, 5, 3, 3)
    offsets = rng.normal(size=(5, 3)).astype(np.float32)
    root = rng.normal(size=(batch, 3)).astype(np.float32)
    fk = jax.jit(geo.forward_kinematics_with_rotations, static_argnums=(3, 4))
    pos, glob = fk(root, local, offsets, PARENTS, ORDER)
    for b in range(batch):
        wp, wg = np_fk(root[b], local[b], offsets, PARENTS, ORDER)
        np.testing.assert_allclose(pos[b], wp, atol=1e-5)
        np.testing.assert_allclose(glob[b], wg, atol=1e-5)
    # Bone lengths are preserved by any rotations (Eq. 1).
    lengths = np.linalg.norm(pos - pos[:, list(PARENTS)], axis=-1)
    np.testing.assert_allclose(
        lengths[:, 1:], np.broadcast_to(np.linalg.norm(offsets[1:], axis=-1), (batch, 4)), rtol=1e-4
    )
    eager = geo.forward_kinematics(root, local, offsets, np.array(PARENTS), list(ORDER))
    np.testing.assert_allclose(eager, pos, atol=1e-5)


def test_fk_vmap_and_per_sample_offsets_and_grad():
    rng = np.random.default_rng(5)
    d6 = jnp.asarray(rng.normal(size=(3, 5, 6)).astype(np.float32))
    offsets = jnp.asarray(rng.normal(size=(3, 5, 3)).astype(np.float32))
    root = jnp.zeros((3, 3))

    def f(d, o, r):
        return geo.forward_kinematics(r, geo.rotation_6d_to_matrix(d), o, PARENTS, ORDER)

    batched = jax.jit(f)(d6, offsets, root)
    mapped = jax.jit(jax.vmap(f))(d6, offsets, root)
    np.testing.assert_allclose(mapped, batched, atol=1e-6)
    check_grads(
        jax.jit(lambda d: f(d, offsets, root).sum()),
        (d6,),
        order=1,
        modes=["rev"],
        atol=5e-2,
        rtol=5e-2,
    )


def test_fk_rejects_bad_trees():
    eye = jnp.broadcast_to(jnp.eye(3), (5, 3, 3))
    with pytest.raises(ValueError, match="topological"):
        geo.forward_kinematics(jnp.zeros(3), eye, jnp.zeros((5, 3)), PARENTS, (0, 3, 1, 2, 4))
    with pytest.raises(ValueError, match="root"):
        geo.forward_kinematics(jnp.zeros(3), eye, jnp.zeros((5, 3)), PARENTS, (1, 0, 2, 3, 4))
    with pytest.raises(ValueError, match="local_rots"):
        geo.forward_kinematics(jnp.zeros(3), eye[:4], jnp.zeros((5, 3)), PARENTS, ORDER)


def test_bone_offsets():
    pos = jnp.asarray(np.random.default_rng(6).normal(size=(5, 3)).astype(np.float32))
    d = geo.bone_offsets(pos, PARENTS)
    np.testing.assert_allclose(d[0], 0.0)
    rebuilt = geo.forward_kinematics(
        pos[0], jnp.broadcast_to(jnp.eye(3), (5, 3, 3)), d, PARENTS, ORDER
    )
    np.testing.assert_allclose(rebuilt, pos, atol=1e-5)
    dirs = jnp.asarray(np.random.default_rng(7).normal(size=(5, 3)).astype(np.float32))
    scaled = geo.bone_offsets(pos, PARENTS, dirs)
    np.testing.assert_allclose(
        np.linalg.norm(scaled, axis=-1), np.linalg.norm(d, axis=-1), rtol=1e-5
    )


def random_tree(rng, k):
    """(parents, order) of a random tree on relabelled nodes: node i (i >= 1) hangs below a random
    earlier node, so the order is topological by construction, root first."""
    label = rng.permutation(k)
    parents = np.zeros(k, int)
    for i in range(k):
        parents[label[i]] = label[rng.integers(0, i)] if i else label[0]
    return parents, label


@SETTINGS
@given(k=st.sampled_from([1, 4, 9]), seed=st.integers(0, 999))
def test_fk_random_trees(k, seed):
    rng = np.random.default_rng(seed)
    parents, order = random_tree(rng, k)
    local = random_rotations(seed, k)
    offsets = rng.normal(size=(k, 3)).astype(np.float32)
    root = rng.normal(size=3).astype(np.float32)
    pos, glob = geo.forward_kinematics_with_rotations(root, local, offsets, parents, order)
    wp, wg = np_fk(root, local, offsets, parents, order)
    np.testing.assert_allclose(pos, wp, atol=1e-4)
    np.testing.assert_allclose(glob, wg, atol=1e-5)
    depth = np.zeros(k, int)
    for j in order[1:]:
        depth[j] = depth[parents[j]] + 1
    levels = geo.tree_levels(parents, order)
    assert len(levels) == depth.max() + 1
    for d, level in enumerate(levels):
        np.testing.assert_array_equal(np.sort(level), np.flatnonzero(depth == d))


def test_degenerate_6d_has_finite_gradient():
    d6 = jnp.array([[0.0, 0, 0, 0, 0, 0], [1.0, 0, 0, 2.0, 0, 0]])  # zero, parallel halves
    g = jax.jit(jax.grad(lambda x: geo.rotation_6d_to_matrix(x).sum()))(d6)
    assert np.all(np.isfinite(g))


def test_6d_near_zero_follows_the_releases_additive_epsilon():
    # x = a1 / (|a1| + 1e-10) = (1e-9 / 1.1e-9, 0, 0); z = x cross a2 = (0, 0, 1/1.1), normalised
    # to (0, 0, 1) up to 1e-10; y = z cross x = (0, 1/1.1, 0). A clamped norm (max(|a1|, eps))
    # would give other values: (0.1, 0, 0) with eps = 1e-8.
    d6 = jnp.array([1e-9, 0.0, 0.0, 0.0, 1.0, 0.0])
    np.testing.assert_allclose(
        geo.rotation_6d_to_matrix(d6), np.diag([1 / 1.1, 1 / 1.1, 1.0]), rtol=1e-6, atol=1e-7
    )


def test_fk_gradient_compiles_with_several_batch_axes_and_vmap():
    # Regression: batched dot_general of gathered operands crashed XLA:CPU's simplifier here.
    d6 = jnp.asarray(np.random.default_rng(8).normal(size=(2, 3, 5, 6)).astype(np.float32))
    offsets = jnp.ones((5, 3))

    def f(d):
        rots = geo.rotation_6d_to_matrix(d)
        return geo.forward_kinematics(jnp.zeros(d.shape[:-2] + (3,)), rots, offsets, PARENTS, ORDER)

    g = jax.jit(jax.grad(lambda d: f(d).sum()))(d6)
    gv = jax.jit(jax.vmap(jax.grad(lambda d: f(d).sum())))(d6)
    np.testing.assert_allclose(gv, g, atol=1e-5)
    assert np.all(np.isfinite(g))


# --- the NumPy twins against their JAX functions ------------------------------------------------


@SETTINGS
@given(seed=st.integers(0, 999))
def test_axis_angle_twin_matches_jax(seed):
    rng = np.random.default_rng(seed)
    w = rng.normal(scale=2.0, size=(4, 6, 3))
    w[0, 0] = 0.0  # the zero rotation
    w[0, 1] = [1e-7, 0.0, -2e-7]  # a tiny one
    got = geo.axis_angle_to_matrix_np(w)
    assert got.dtype == np.float64 and got.shape == (4, 6, 3, 3)
    want = np.asarray(geo.axis_angle_to_matrix(jnp.asarray(w, jnp.float32)))
    np.testing.assert_allclose(got, want, atol=2e-6)
    np.testing.assert_array_equal(got[0, 0], np.eye(3))
    # The (axis, angle) form: any axis length, any sign of the angle.
    angle = rng.normal(scale=3.0, size=(4, 6))
    axis = rng.normal(size=(4, 6, 3))
    unit = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    np.testing.assert_allclose(
        geo.axis_angle_to_matrix_np(axis, angle),
        geo.axis_angle_to_matrix_np(unit * angle[..., None]),
        atol=1e-12,
    )


@SETTINGS
@given(seed=st.integers(0, 999))
def test_align_rotation_twin_matches_jax(seed):
    rng = np.random.default_rng(seed)
    u, v = rng.normal(size=(2, 3, 8, 3))
    v[0, 0] = -3.0 * u[0, 0]  # antiparallel
    v[0, 1] = 0.5 * u[0, 1]  # parallel
    got = geo.align_rotation_np(u, v)
    assert got.dtype == np.float64 and got.shape == (3, 8, 3, 3)
    # The twin is the same formula in float64: compared with the JAX function in float64, since
    # float32 rounding of a near-antiparallel pair alone moves the result by ~3e-5.
    with jax.enable_x64(True):
        want = geo.align_rotation(jnp.asarray(u, jnp.float64), jnp.asarray(v, jnp.float64))
    np.testing.assert_allclose(got, want, atol=1e-9)
    turned = np.einsum("...ij,...j->...i", got, u / np.linalg.norm(u, axis=-1, keepdims=True))
    np.testing.assert_allclose(turned, v / np.linalg.norm(v, axis=-1, keepdims=True), atol=1e-12)
    # A zero vector on either side: the identity (the JAX function's too).
    np.testing.assert_array_equal(geo.align_rotation_np(np.zeros(3), v[1, 2]), np.eye(3))
    np.testing.assert_allclose(geo.align_rotation(jnp.zeros(3), jnp.ones(3)), np.eye(3))


@SETTINGS
@given(k=st.sampled_from([1, 5, 9]), seed=st.integers(0, 999), batch=st.sampled_from([(), (2, 3)]))
def test_forward_kinematics_twin_matches_jax(k, seed, batch):
    rng = np.random.default_rng(seed)
    parents, order = random_tree(rng, k)
    local = Rotation.random(int(np.prod(batch, dtype=int)) * k, random_state=seed).as_matrix()
    local = local.reshape(*batch, k, 3, 3)
    offsets = rng.normal(size=(*batch, k, 3))
    root = rng.normal(size=(*batch, 3))
    pos, glob = geo.forward_kinematics_np(root, local, offsets, parents, order)
    jax_pos, jax_glob = geo.forward_kinematics_with_rotations(
        *(jnp.asarray(a, jnp.float32) for a in (root, local, offsets)), parents, order
    )
    assert pos.shape == (*batch, k, 3) and glob.shape == (*batch, k, 3, 3)
    np.testing.assert_allclose(pos, jax_pos, atol=1e-4)
    np.testing.assert_allclose(glob, jax_glob, atol=1e-5)
    # Offsets in the parent's frame: "own" offsets turned by each joint's local rotation first.
    turned = np.einsum("...kij,...kj->...ki", local, offsets)
    parent_pos, parent_glob = geo.forward_kinematics_np(
        root, local, turned, parents, order, offset_frame="parent"
    )
    np.testing.assert_allclose(parent_pos, pos, atol=1e-12)
    np.testing.assert_array_equal(parent_glob, glob)
    if k > 1:  # the two frames differ when the offsets are not turned
        other, _ = geo.forward_kinematics_np(
            root, local, offsets, parents, order, offset_frame="parent"
        )
        assert not np.allclose(other, pos)


def test_forward_kinematics_twin_refuses_bad_input():
    eye = np.broadcast_to(np.eye(3), (5, 3, 3))
    with pytest.raises(ValueError, match="topological"):
        geo.forward_kinematics_np(np.zeros(3), eye, np.zeros((5, 3)), PARENTS, (0, 3, 1, 2, 4))
    with pytest.raises(ValueError, match="offsets must be"):
        geo.forward_kinematics_np(np.zeros(3), eye, np.zeros((4, 3)), PARENTS, ORDER)
    with pytest.raises(ValueError, match="offset_frame"):
        geo.forward_kinematics_np(
            np.zeros(3), eye, np.zeros((5, 3)), PARENTS, ORDER, offset_frame="x"
        )


@SETTINGS
@given(seed=st.integers(0, 999))
def test_linear_blend_skinning_twin_matches_jax(seed):
    rng = np.random.default_rng(seed)
    vertices = rng.normal(size=(40, 3))
    weights = rng.dirichlet(np.ones(4), size=40)
    rotations = Rotation.random(2 * 3 * 4, random_state=seed).as_matrix().reshape(2, 3, 4, 3, 3)
    translations = rng.normal(size=(2, 3, 4, 3))
    got = geo.linear_blend_skinning_np(vertices, weights, rotations, translations)
    want = geo.linear_blend_skinning(
        *(jnp.asarray(a, jnp.float32) for a in (vertices, weights)),
        rotations=jnp.asarray(rotations, jnp.float32),
        translations=jnp.asarray(translations, jnp.float32),
    )
    assert got.shape == (2, 3, 40, 3)
    np.testing.assert_allclose(got, want, atol=1e-5)
    # Per-frame rest vertices (SMPL's pose blend shapes): each frame skins its own.
    per_frame = vertices + rng.normal(scale=0.1, size=(2, 3, 40, 3))
    batched = geo.linear_blend_skinning_np(per_frame, weights, rotations, translations)
    one = geo.linear_blend_skinning_np(
        per_frame[1, 2], weights, rotations[1, 2], translations[1, 2]
    )
    np.testing.assert_allclose(batched[1, 2], one, atol=1e-12)
