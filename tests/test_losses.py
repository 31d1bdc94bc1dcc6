import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

from nmjax import losses
from nmjax.config import LossWeights

SETTINGS = settings(max_examples=8, deadline=None)


def random_keypoints(rng, shape):
    mu = rng.uniform(-1, 1, (*shape, 3))
    alpha = rng.uniform(0, 1, (*shape, 1))
    return np.concatenate([mu, alpha], -1).astype(np.float32)


def random_affinity(rng, n, k):
    return np.asarray(losses.affinity_from_params(jnp.asarray(rng.normal(size=(n, k, k - 1)))))


# --- independent NumPy references --------------------------------------------------------------


def np_pair_sq(mu):
    return ((mu[..., :, None, :] - mu[..., None, :, :]) ** 2).sum(-1)


def np_separation(kp, sigma):
    mu = kp[..., :3]
    s = mu - mu.mean(-3, keepdims=True)
    b, t, k, _ = kp.shape
    out = np.zeros(b)
    for i in range(b):
        for a in range(k):
            for c in range(k):
                if a != c:
                    d = np.mean(((s[i, :, a] - s[i, :, c]) ** 2).sum(-1))
                    out[i] += np.exp(-d / (2 * sigma**2))
    return out / (k * (k - 1))


def np_volume(vox, kp):
    g = vox.shape[-1]
    x = np.linspace(-1, 1, g)
    out = np.zeros(vox.shape[:-3])
    for idx in np.ndindex(*vox.shape[:-3]):
        cells = np.argwhere(vox[idx] > 0)
        if len(cells) == 0:
            continue
        p = x[cells]
        d = ((p[:, None] - kp[idx][None, :, :3]) ** 2).sum(-1).min(1)
        out[idx] = d.mean()
    return out


def np_trajectory_cost(kp):
    mu = kp[..., :3].reshape(-1, *kp.shape[-3:-1], 3)
    vel = np.diff(mu, axis=1)
    acc = np.diff(vel, axis=1)

    def cos(u):
        n = np.maximum(np.linalg.norm(u, axis=-1), 1e-6)
        un = u / n[..., None]
        return np.einsum("btkd,btld->btkl", un, un)

    return 1.0 - (cos(vel).mean((0, 1)) + cos(acc).mean((0, 1))) / 2


# --- analytic cases ----------------------------------------------------------------------------


def test_separation_identical_and_far():
    rng = np.random.default_rng(0)
    traj = rng.uniform(-1, 1, (1, 5, 1, 3))
    same = np.concatenate([np.repeat(traj, 4, axis=2), np.ones((1, 5, 4, 1))], -1)
    np.testing.assert_allclose(losses.separation(jnp.asarray(same)), [1.0], atol=1e-6)
    # Centred trajectories far apart: keypoint k oscillates along its own direction.
    t = np.linspace(-1, 1, 5)
    far = np.zeros((1, 5, 3, 4), np.float32)
    for k in range(3):
        far[0, :, k, k] = t * (k + 1) * 0.5
    assert float(losses.separation(jnp.asarray(far))[0]) < 1e-10


def test_volume_fitting_zero_when_keypoints_cover_voxels():
    g = 8
    x = np.linspace(-1, 1, g)
    vox = np.zeros((2, g, g, g), np.float32)
    cells = [[(1, 2, 3), (5, 5, 5)], [(0, 0, 0), (7, 1, 4)]]
    kp = np.zeros((2, 3, 4), np.float32)
    for f in range(2):
        for i, c in enumerate(cells[f]):
            vox[(f, *c)] = 1
            kp[f, i, :3] = x[list(c)]
        kp[f, 2, :3] = 0.9  # an extra keypoint away from the voxels changes nothing
    np.testing.assert_allclose(
        losses.volume_fitting(jnp.asarray(vox), jnp.asarray(kp)), 0.0, atol=1e-6
    )
    empty = losses.volume_fitting(jnp.zeros((1, g, g, g)), jnp.asarray(kp[:1]))
    np.testing.assert_allclose(empty, 0.0)


def test_graph_complexity_disjoint_and_overlap():
    k = 4
    a0 = np.eye(k)[[1, 2, 3, 0]]  # one-hot neighbour k -> k+1
    a1 = np.eye(k)[[3, 0, 1, 2]]  # one-hot neighbour k -> k-1: disjoint support
    assert float(losses.graph_complexity(jnp.asarray(np.stack([a0, a1])))) == 0.0
    # Identical one-hot matrices: 2 ordered pairs x K ones / K^2 entries.
    same = jnp.asarray(np.stack([a0, a0]))
    np.testing.assert_allclose(losses.graph_complexity(same), 2 * k / k**2, rtol=1e-6)


def test_trajectory_cost_parallel_and_opposite():
    t = np.arange(6, dtype=np.float32)[:, None]
    direction = np.array([0.3, -0.2, 0.5], np.float32)
    path = t**2 * direction  # accelerating, so accelerations are non-zero too
    ones = np.ones((6, 1), np.float32)
    parallel = np.stack([np.c_[path, ones], np.c_[path + 1.0, ones]], axis=1)[None]
    opposite = np.stack([np.c_[path, ones], np.c_[-path, ones]], axis=1)[None]
    np.testing.assert_allclose(losses.trajectory_cost(jnp.asarray(parallel)), 0.0, atol=1e-6)
    # Opposite velocities and accelerations: (1 - (-1)) / 2 + (1 - (-1)) / 2 = 2 (the released
    # scale, docs/architecture.md §5); the printed Eq. 14's scale halves it.
    cost = np.asarray(losses.trajectory_cost(jnp.asarray(opposite)))
    np.testing.assert_allclose(cost, [[0.0, 2.0], [2.0, 0.0]], atol=1e-6)
    printed = np.asarray(losses.trajectory_cost(jnp.asarray(opposite), printed_scale=True))
    np.testing.assert_allclose(printed, [[0.0, 1.0], [1.0, 0.0]], atol=1e-6)
    a = jnp.array([[0.0, 1.0], [1.0, 0.0]])
    np.testing.assert_allclose(losses.graph_trajectory(jnp.asarray(opposite), a), 1.0, atol=1e-6)
    np.testing.assert_allclose(losses.graph_trajectory(jnp.asarray(parallel), a), 0.0, atol=1e-6)


def test_trajectory_cost_two_keypoints_known_cosine():
    # Keypoint 0 moves along x with velocities 1, 2, 4 (accelerations 1, 2: along x); keypoint 1
    # moves along (1, 1, 0)/sqrt(2) with the same speeds. cos(vel) = cos(acc) = 1/sqrt(2) in
    # every frame, so C_01 = 2 (1 - 1/sqrt(2)) / 2 = 1 - 1/sqrt(2) = 0.2929.
    steps = np.array([0.0, 1.0, 3.0, 7.0], np.float32)[:, None]
    along_x = steps * np.array([1.0, 0.0, 0.0], np.float32)
    diagonal = steps * np.array([1.0, 1.0, 0.0], np.float32) / np.sqrt(2)
    ones = np.ones((4, 1), np.float32)
    kp = np.stack([np.c_[along_x, ones], np.c_[diagonal, ones]], axis=1)[None]  # (1, 4, 2, 4)
    cost = np.asarray(losses.trajectory_cost(jnp.asarray(kp)))
    np.testing.assert_allclose(cost[0, 1], 1 - 1 / np.sqrt(2), rtol=1e-5)
    np.testing.assert_allclose(cost, cost.T, atol=1e-7)


def test_cosine_clamps_a_short_norm_in_value_but_not_in_its_gradient():
    # PyTorch's cosine similarity (the release's L_traj) clamps each norm to eps in place outside
    # autograd. For u = s x with s = 5e-7 < eps = 1e-6 and v = x (unit):
    # cos = u.v / (eps |v|) = s / eps = 0.5, and d cos / du = v / eps - (u.v) / eps^2 * u / |u|
    # = (1 / eps - s / eps^2) x = 5e5 x; a clamp that stopped the norm's gradient would give 1e6 x.
    s, eps = 5e-7, losses.COS_EPS
    u = jnp.array([[s, 0.0, 0.0]], jnp.float32)
    v = jnp.array([[1.0, 0.0, 0.0]], jnp.float32)
    np.testing.assert_allclose(losses._cosine(u, v)[0, 0], s / eps, rtol=1e-5)
    grad = jax.grad(lambda u: losses._cosine(u, v)[0, 0])(u)
    np.testing.assert_allclose(grad, [[1 / eps - s / eps**2, 0.0, 0.0]], rtol=1e-4)
    # A keypoint standing still (u = 0): cosine 0, gradient v / eps (the norm's gradient at 0 is 0).
    zero = jnp.zeros((1, 3), jnp.float32)
    assert float(losses._cosine(zero, v)[0, 0]) == 0.0
    np.testing.assert_allclose(
        jax.grad(lambda u: losses._cosine(u, v)[0, 0])(zero), [[1 / eps, 0.0, 0.0]], rtol=1e-5
    )


def test_affinity_from_params_layout():
    p = jnp.arange(2 * 4 * 3, dtype=jnp.float32).reshape(2, 4, 3)
    a = np.asarray(losses.affinity_from_params(p))
    soft = np.asarray(jax.nn.softmax(p, axis=-1))
    np.testing.assert_allclose(np.diagonal(a, axis1=1, axis2=2), 0.0)
    np.testing.assert_allclose(a.sum(-1), 1.0, rtol=1e-6)
    for n in range(2):
        for i in range(4):
            np.testing.assert_allclose(np.delete(a[n, i], i), soft[n, i], rtol=1e-6)
    with pytest.raises(ValueError, match="K, K-1"):
        losses.affinity_from_params(jnp.ones((2, 4, 4)))


def test_reconstruction_and_sparsity_values():
    v = jnp.array([[[[1.0, 0.0]] * 2] * 2])  # (1, 2, 2, 2)
    r = jnp.full_like(v, 0.25)
    want = -(0.5 * np.log(0.25) + 0.5 * np.log(0.75))
    np.testing.assert_allclose(losses.reconstruction_bce(v, r), [want], rtol=1e-6)
    assert np.isfinite(losses.reconstruction_bce(v, 1.0 - v)).all()  # saturated: clipped, finite
    heat = jnp.stack([jnp.full((3, 3, 3), 2.0), jnp.full((3, 3, 3), 4.0)], -1)[None]
    np.testing.assert_allclose(losses.heatmap_sparsity(heat), [3.0])


def test_kl_and_vrnn_reconstruction():
    mq, sq = jnp.array([[0.5, -1.0]]), jnp.array([[1.0, 0.5]])
    mp, sp = jnp.array([[0.0, 0.0]]), jnp.array([[1.0, 2.0]])
    want = (
        np.log(np.array([1.0, 2.0]) / np.array([1.0, 0.5]))
        + (np.array([1.0, 0.25]) + np.array([0.25, 1.0])) / (2 * np.array([1.0, 4.0]))
        - 0.5
    )
    np.testing.assert_allclose(
        losses.kl_diag_gaussians(mq, sq, mp, sp, axis=None), [want], rtol=1e-5
    )
    np.testing.assert_allclose(losses.kl_diag_gaussians(mq, sq, mp, sp), [want.sum()], rtol=1e-5)
    np.testing.assert_allclose(losses.kl_diag_gaussians(mq, sq, mq, sq), [0.0], atol=1e-7)
    x = jnp.zeros((2, 3, 4, 4))
    np.testing.assert_allclose(losses.vrnn_reconstruction(x, x + 0.5), 16 * 0.25)
    np.testing.assert_allclose(
        losses.vrnn_reconstruction(x.reshape(2, 3, 16), x.reshape(2, 3, 16) + 0.5, 1), 4.0
    )


# --- property tests against NumPy --------------------------------------------------------------


@jax.jit
def _jitted_terms(kp, a):
    return {
        "sep": losses.separation(kp, 0.5),
        "local": losses.graph_local(kp, a),
        "local_w": losses.graph_local(kp, a, True),
        "time": losses.graph_time(kp, a),
        "traj": losses.trajectory_cost(kp),
        "complex": losses.graph_complexity(a),
    }


@SETTINGS
@given(
    b=st.sampled_from([1, 2]),
    t=st.sampled_from([3, 4]),
    k=st.sampled_from([2, 4]),
    seed=st.integers(0, 999),
)
def test_keypoint_losses_match_numpy(b, t, k, seed):
    rng = np.random.default_rng(seed)
    kp = random_keypoints(rng, (b, t, k))
    a = random_affinity(rng, 2, k)
    infl = a.max(0)
    mu, alpha = kp[..., :3], kp[..., 3]
    dist = np_pair_sq(mu)
    got = _jitted_terms(jnp.asarray(kp), jnp.asarray(a))
    np.testing.assert_allclose(got["sep"], np_separation(kp, 0.5), rtol=1e-4)
    np.testing.assert_allclose(got["local"], (infl * dist).mean((-2, -1)), rtol=1e-4)
    weighted = (infl * dist * alpha[..., :, None]).mean((-2, -1))
    np.testing.assert_allclose(got["local_w"], weighted, rtol=1e-4)
    dev = np.abs(dist - dist.mean(1, keepdims=True))
    np.testing.assert_allclose(got["time"], (infl * dev).mean((-2, -1)), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(got["traj"], np_trajectory_cost(kp), rtol=1e-4, atol=1e-5)
    cross = sum((a[i] * a[j]) ** 2 for i in range(2) for j in range(2) if i != j)
    np.testing.assert_allclose(got["complex"], cross.mean(), rtol=1e-5)


@SETTINGS
@given(
    lead=st.sampled_from([1, 3]),
    g=st.sampled_from([2, 5]),
    k=st.sampled_from([1, 4]),
    seed=st.integers(0, 999),
)
def test_volume_fitting_matches_numpy(lead, g, k, seed):
    rng = np.random.default_rng(seed)
    vox = (rng.random((lead, 2, g, g, g)) < 0.3).astype(np.float32)
    kp = random_keypoints(rng, (lead, 2, k))
    got = jax.jit(losses.volume_fitting)(jnp.asarray(vox), jnp.asarray(kp))
    assert got.shape == (lead, 2)
    np.testing.assert_allclose(got, np_volume(vox, kp), rtol=1e-4, atol=1e-6)


def test_jit_equals_eager_and_vmap():
    rng = np.random.default_rng(1)
    b, t, k, g, hg = 2, 4, 5, 6, 3
    outputs = {
        "voxels": jnp.asarray((rng.random((b, t, g, g, g)) < 0.3).astype(np.float32)),
        "recon": jnp.asarray(rng.uniform(0.01, 0.99, (b, t, g, g, g)).astype(np.float32)),
        "heatmaps": jnp.asarray(rng.random((b, t, hg, hg, hg, k)).astype(np.float32)),
        "keypoints": jnp.asarray(random_keypoints(rng, (b, t, k))),
        "affinity": jnp.asarray(random_affinity(rng, 2, k)),
    }
    weights = LossWeights()
    total, terms = losses.skeleton_loss(outputs, weights)
    jitted = jax.jit(losses.skeleton_loss, static_argnums=1)
    jtotal, jterms = jitted(outputs, weights)
    np.testing.assert_allclose(jtotal, total, rtol=1e-5)
    assert set(terms) == set(losses.TERMS)
    for name in losses.TERMS:
        np.testing.assert_allclose(jterms[name], terms[name], rtol=1e-5, atol=1e-7)
    want = sum(getattr(weights, n) * float(v) for n, v in terms.items())
    np.testing.assert_allclose(total, want, rtol=1e-5)
    # Intensity-weighted variant: the three graph terms change, the others do not.
    weighted = dataclasses.replace(weights, intensity_weighted=True)
    wtotal, wterms = jitted(outputs, weighted)
    for name in losses.TERMS:
        same = name not in ("local", "time", "traj")
        assert np.isclose(wterms[name], terms[name], rtol=1e-6) == same, name
    want = sum(getattr(weighted, n) * float(v) for n, v in wterms.items())
    np.testing.assert_allclose(wtotal, want, rtol=1e-5)
    per_seq = jax.vmap(lambda kp: losses.separation(kp[None])[0])(outputs["keypoints"])
    np.testing.assert_allclose(per_seq, losses.separation(outputs["keypoints"]), rtol=1e-6)
    with pytest.raises(ValueError, match="affinity"):
        losses.skeleton_loss({k: v for k, v in outputs.items() if k != "affinity"}, LossWeights())


# --- gradients ---------------------------------------------------------------------------------


def check_grads_jit(f, args, **kwargs):
    check_grads(jax.jit(f), args, **kwargs)


def test_check_grads_smooth_losses():
    rng = np.random.default_rng(2)
    kp = jnp.asarray(random_keypoints(rng, (1, 4, 3)))
    a = jnp.asarray(random_affinity(rng, 2, 3))
    params = jnp.asarray(rng.normal(size=(2, 3, 2)))
    v = jnp.asarray((rng.random((1, 3, 3, 3)) < 0.5).astype(np.float32))
    r = jnp.asarray(rng.uniform(0.2, 0.8, (1, 3, 3, 3)))
    heat = jnp.asarray(rng.uniform(0.5, 1.0, (1, 2, 2, 2, 3)))
    mq, sq, mp, sp = (jnp.asarray(rng.uniform(0.5, 1.5, 4)) for _ in range(4))
    tol = dict(order=1, modes=["rev"], atol=5e-2, rtol=5e-2)
    check_grads_jit(lambda x: losses.separation(x, 0.5).sum(), (kp,), **tol)
    check_grads_jit(lambda x, y: losses.graph_local(x, y, True).sum(), (kp, a), **tol)
    check_grads_jit(lambda x: losses.trajectory_cost(x).sum(), (kp,), **tol)
    check_grads_jit(
        lambda p: losses.graph_complexity(losses.affinity_from_params(p)), (params,), **tol
    )
    check_grads_jit(lambda y: losses.reconstruction_bce(v, y).sum(), (r,), **tol)
    check_grads_jit(lambda h: losses.heatmap_sparsity(h).sum(), (heat,), **tol)
    check_grads_jit(lambda *z: losses.kl_diag_gaussians(*z), (mq, sq, mp, sp), **tol)


def test_volume_fitting_gradient_matches_numpy():
    # d/dmu_k = sum over the cells nearest to k of 2 (mu_k - p), over the occupied count.
    rng = np.random.default_rng(3)
    g, k = 5, 3
    vox = (rng.random((1, g, g, g)) < 0.4).astype(np.float32)
    kp = random_keypoints(rng, (1, k))
    grad = np.asarray(jax.grad(lambda x: losses.volume_fitting(jnp.asarray(vox), x).sum())(kp))
    x = np.linspace(-1, 1, g)
    p = x[np.argwhere(vox[0] > 0)]
    nearest = ((p[:, None] - kp[0, None, :, :3]) ** 2).sum(-1).argmin(1)
    want = np.zeros((k, 3))
    for j in range(k):
        want[j] = 2 * (kp[0, j, :3] - p[nearest == j]).sum(0) / len(p)
    np.testing.assert_allclose(grad[0, :, :3], want, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(grad[0, :, 3], 0.0)


def test_gradients_finite_with_coincident_keypoints_and_zero_velocity():
    k, t = 4, 5
    still = jnp.zeros((2, t, k, 4)).at[..., 3].set(0.5)  # all keypoints coincide, never move
    rng = np.random.default_rng(4)
    params = jnp.asarray(rng.normal(size=(2, k, k - 1)).astype(np.float32))
    vox = jnp.asarray((rng.random((2, t, 4, 4, 4)) < 0.5).astype(np.float32))

    def total(kp, p):
        a = losses.affinity_from_params(p)
        out = {
            "voxels": vox,
            "recon": jnp.clip(vox, 0.0, 1.0),  # saturated reconstruction
            "heatmaps": jnp.zeros((2, t, 2, 2, 2, k)),
            "keypoints": kp,
            "affinity": a,
        }
        return losses.skeleton_loss(out, LossWeights(intensity_weighted=True))[0]

    grad = jax.jit(jax.grad(total, argnums=(0, 1)))
    for kp in (still, jnp.asarray(random_keypoints(rng, (2, t, k)))):
        gk, gp = grad(kp, params)
        assert np.all(np.isfinite(gk)) and np.all(np.isfinite(gp))


def test_volume_fitting_memory_at_paper_scale():
    # G=64, K=28, B=3, T=10 forward + gradient: compiled (not run) to read XLA's buffer plan.
    voxels = jax.ShapeDtypeStruct((3, 10, 64, 64, 64), jnp.float32)
    kp = jax.ShapeDtypeStruct((3, 10, 28, 4), jnp.float32)
    fn = jax.jit(jax.value_and_grad(lambda v, x: losses.volume_fitting(v, x).mean(), argnums=1))
    stats = fn.lower(voxels, kp).compile().memory_analysis()
    total = stats.temp_size_in_bytes + stats.argument_size_in_bytes + stats.output_size_in_bytes
    assert total < 512 * 2**20  # well under the 1.5 GB budget (about 220 MiB)
