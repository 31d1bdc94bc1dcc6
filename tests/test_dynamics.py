"""Tests of nmjax.models.dynamics: shapes, FK decoder, fixed offsets, best-of-S, generation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from nmjax import geometry
from nmjax.config import DynamicsConfig
from nmjax.models import dynamics
from nmjax.models.dynamics import Buffer, Dynamics, bone_lengths

PARENTS = (1, 1, 0, 1, 3)  # root 1; 1 -> 0 -> 2 and 1 -> 3 -> 4
ORDER = (1, 0, 3, 2, 4)
K = len(PARENTS)
TINY = DynamicsConfig(latent=4, hidden=8, mlp=8, posterior_samples=3)


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' formula."""
    axis = axis / np.linalg.norm(axis)
    skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * skew + (1 - np.cos(angle)) * skew @ skew


def numpy_fk(root: np.ndarray, local: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Eq. 2 joint by joint: root (3,), local (K,3,3), offsets (K,3) -> (K,3)."""
    glob, pos = np.zeros((K, 3, 3)), np.zeros((K, 3))
    for k in ORDER:
        p = PARENTS[k]
        if p == k:
            glob[k], pos[k] = local[k], root
        else:
            glob[k] = glob[p] @ local[k]
            pos[k] = pos[p] + glob[k] @ offsets[k]
    return pos


def make_model(model: str = "nm", seed: int = 0, cfg: DynamicsConfig = TINY) -> Dynamics:
    cfg = DynamicsConfig(**{**cfg.__dict__, "model": model})
    return Dynamics(cfg, PARENTS, ORDER, rngs=nnx.Rngs(seed))


def random_sequence(batch: int, frames: int, seed: int = 0) -> np.ndarray:
    """(B,T,K,4) keypoints of the test tree under random rotations, alpha in (0,1)."""
    rng = np.random.default_rng(seed)
    offsets = rng.normal(size=(K, 3)) * 0.2
    x = np.zeros((batch, frames, K, 4), np.float32)
    for b in range(batch):
        for t in range(frames):
            local = np.stack([rotation_about(rng.normal(size=3), rng.uniform(0, 1)) for _ in ORDER])
            x[b, t, :, :3] = numpy_fk(rng.uniform(-0.3, 0.3, 3), local, offsets)
    x[..., 3] = rng.uniform(0.2, 0.9, size=(batch, frames, K))
    return x


@pytest.mark.parametrize("kind", ["nm", "vrnn"])
def test_shapes(kind):
    model = make_model(kind)
    x = jnp.asarray(random_sequence(2, 5))
    out = model(x, jax.random.key(0))
    assert out.keypoints.shape == (2, 5, K, 4)
    assert out.rotations.shape == (2, 5, K, 3, 3)
    for field in (out.z, out.mean_q, out.std_q, out.mean_p, out.std_p):
        assert field.shape == (2, 5, TINY.latent)
    assert bool(jnp.all(out.std_q >= dynamics.STD_EPS)) and bool(jnp.all(out.std_p > 0))
    keypoints, rotations = model.generate(x[:, :2], 4, jax.random.key(1))
    assert keypoints.shape == (2, 6, K, 4) and rotations.shape == (2, 6, K, 3, 3)
    if kind == "vrnn":  # same scan as __call__ (compiled once more per S)
        recon, _ = model.reconstruct(x, jax.random.key(2))
        assert recon.shape == x.shape
    alpha = out.keypoints[..., 3]
    if kind == "nm":
        assert bool(jnp.all((alpha >= 0) & (alpha <= 1)))
        np.testing.assert_allclose(
            jnp.einsum("...ij,...kj->...ik", out.rotations, out.rotations),
            np.broadcast_to(np.eye(3), out.rotations.shape),
            atol=1e-5,
        )
    else:
        np.testing.assert_array_equal(out.rotations, np.broadcast_to(np.eye(3), (2, 5, K, 3, 3)))


def test_bone_lengths_is_median_of_parent_distances():
    x = random_sequence(2, 7, seed=3)
    expected = np.median(np.linalg.norm(x[..., :3] - x[..., PARENTS, :3], axis=-1), axis=1)
    np.testing.assert_allclose(bone_lengths(jnp.asarray(x), PARENTS), expected, rtol=1e-6)
    assert np.all(expected[:, 1] == 0)  # the root is its own parent


def test_decoder_fk_with_identity_rotations():
    """Zeroed decoder kernels: identity 6D rotations and a chosen root; FK must sum the offsets."""
    model = make_model("nm")
    root = np.array([0.1, -0.2, 0.3], np.float32)
    alpha_raw = np.linspace(-0.5, 0.5, K).astype(np.float32)
    g_out, r_out = model.global_decoder.out, model.rotation_decoder.out
    g_out.kernel[...] = jnp.zeros_like(g_out.kernel[...])
    g_out.bias[...] = jnp.asarray(np.arctanh(np.concatenate([root, alpha_raw])))
    r_out.kernel[...] = jnp.zeros_like(r_out.kernel[...])
    # The identity's 6D vector (its first two columns) for every joint.
    r_out.bias[...] = jnp.tile(jnp.array([1.0, 0, 0, 0, 1, 0]), K)
    lengths = jnp.asarray(np.random.default_rng(0).uniform(0.1, 0.5, (2, K)), jnp.float32)
    h = jnp.ones((2, TINY.hidden))
    z = jnp.ones((2, TINY.latent))
    keypoints, rotations = model.decode(h, z, lengths)
    np.testing.assert_allclose(rotations, np.broadcast_to(np.eye(3), (2, K, 3, 3)), atol=1e-6)
    directions = np.asarray(model.directions[...])
    for b in range(2):
        offsets = directions * np.asarray(lengths[b])[:, None]
        expected = np.zeros((K, 3))
        for k in range(K):  # root + sum of the offsets on the path from the root
            expected[k] = root
            j = k
            while PARENTS[j] != j:
                expected[k] += offsets[j]
                j = PARENTS[j]
        np.testing.assert_allclose(keypoints[b, :, :3], expected, atol=1e-5)
        np.testing.assert_allclose(keypoints[b, :, 3], (alpha_raw + 1) / 2, atol=1e-6)


def test_decoder_matches_numpy_fk_for_random_rotations():
    model = make_model("nm", seed=4)
    h = jax.random.normal(jax.random.key(0), (1, TINY.hidden))
    z = jax.random.normal(jax.random.key(1), (1, TINY.latent))
    lengths = jnp.full((1, K), 0.3)
    keypoints, rotations = model.decode(h, z, lengths)
    hz = jnp.concatenate([h, z], -1)
    root = np.tanh(np.asarray(model.global_decoder(hz)))[0, :3]
    offsets = np.asarray(model.directions[...]) * 0.3
    expected = numpy_fk(root, np.asarray(rotations[0], np.float64), offsets)
    np.testing.assert_allclose(keypoints[0, :, :3], expected, atol=1e-5)


def test_offset_directions_are_fixed_unit_buffers():
    model = make_model("nm", seed=7)
    directions = np.asarray(model.directions[...])
    assert isinstance(model.directions, Buffer) and not isinstance(model.directions, nnx.Param)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=-1), 1.0, rtol=1e-6)
    params = nnx.state(model, nnx.Param)
    assert "directions" not in params and "directions" in nnx.state(model, Buffer)
    np.testing.assert_array_equal(directions, make_model("nm", seed=7).directions[...])
    assert not np.allclose(directions, make_model("nm", seed=8).directions[...])
    # gradients never reach the directions
    lengths = jnp.full((1, K), 0.3)
    grads = nnx.grad(lambda m: jnp.sum(m.decode(jnp.ones((1, 8)), jnp.ones((1, 4)), lengths)[0]))(
        model
    )
    assert "directions" not in grads and "rotation_decoder" in grads


def test_best_of_s_keeps_the_closest_sample():
    model = make_model("nm", seed=1, cfg=DynamicsConfig(latent=4, hidden=8, mlp=8))
    x = jnp.asarray(random_sequence(3, 1, seed=5)[:, 0])
    h = jax.random.normal(jax.random.key(2), (3, 8))
    lengths = jnp.full((3, K), 0.2)
    key, samples = jax.random.key(9), 6

    @nnx.jit
    def kept_and_candidates(m):
        _, out = m.posterior_step(h, x, lengths, key, samples)
        mean_q, std_q = m.posterior_dist(h, x)
        z_all = mean_q + std_q * jax.random.normal(key, (samples, 3, 4))
        decoded, _ = m.decode(jnp.broadcast_to(h, (samples, 3, 8)), z_all, lengths[None])
        return out, z_all, decoded

    out, z_all, decoded = kept_and_candidates(model)
    errors = np.sum((np.asarray(decoded) - np.asarray(x)) ** 2, axis=(-2, -1))  # (S, B)
    best = errors.argmin(0)
    np.testing.assert_allclose(out.z, np.asarray(z_all)[best, np.arange(3)], rtol=1e-6)
    np.testing.assert_allclose(
        np.sum((np.asarray(out.keypoints) - x) ** 2, (-2, -1)), errors.min(0), rtol=1e-5
    )


def test_generation_keeps_bone_lengths_and_is_finite():
    model = make_model("nm", seed=2)
    x = jnp.asarray(random_sequence(2, 4, seed=6))
    keypoints, rotations = jax.jit(model.generate, static_argnums=1)(x, 8, jax.random.key(0))
    assert bool(jnp.all(jnp.isfinite(keypoints))) and bool(jnp.all(jnp.isfinite(rotations)))
    lengths = np.linalg.norm(keypoints[..., :3] - keypoints[..., PARENTS, :3], axis=-1)
    expected = np.asarray(bone_lengths(x, PARENTS))[:, None, :]
    np.testing.assert_allclose(lengths, np.broadcast_to(expected, lengths.shape), atol=1e-5)


def test_bad_configuration_is_refused():
    with pytest.raises(ValueError, match="valid models"):
        make_model("lstm")
    with pytest.raises(ValueError, match="permutation"):
        Dynamics(TINY, PARENTS, (0, 1, 2, 3, 4), rngs=nnx.Rngs(0))


def test_best_of_s_gradient_equals_differentiating_all_samples():
    """Decoding the kept sample again gives the gradient of picking among S differentiable ones."""
    model = make_model("nm", seed=3, cfg=DynamicsConfig(latent=4, hidden=8, mlp=8))
    x = jnp.asarray(random_sequence(2, 1, seed=8)[:, 0])
    h = jax.random.normal(jax.random.key(4), (2, 8))
    lengths = jnp.full((2, K), 0.25)
    key, samples = jax.random.key(5), 4

    def kept_loss(m):
        _, out = m.posterior_step(h, x, lengths, key, samples)
        return jnp.sum((out.keypoints - x) ** 2)

    def reference_loss(m):  # every candidate decoded with gradient, then the closest picked
        mean_q, std_q = m.posterior_dist(h, x)
        z_all = mean_q + std_q * jax.random.normal(key, (samples, 2, 4))
        x_all, _ = m.decode(jnp.broadcast_to(h, (samples, 2, 8)), z_all, lengths[None])
        error = jnp.sum((x_all - x) ** 2, axis=(-2, -1))  # (S, B)
        return jnp.sum(jnp.min(error, axis=0))

    got = nnx.jit(nnx.grad(kept_loss))(model)
    expected = nnx.jit(nnx.grad(reference_loss))(model)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(expected), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
    assert any(float(jnp.abs(g).sum()) > 0 for g in jax.tree.leaves(got))


# --- the release's model (docs/architecture.md §8): each difference pinned without the release ----


def test_mlp_hidden_activation_is_leaky_relu_with_slope_0_01():
    mlp = dynamics.MLP(1, 2, 1, rngs=nnx.Rngs(0))
    mlp.hidden.kernel[...] = jnp.array([[1.0, -1.0]])  # units x and -x
    mlp.hidden.bias[...] = jnp.zeros(2)
    mlp.out.kernel[...] = jnp.array([[1.0], [1.0]])
    mlp.out.bias[...] = jnp.zeros(1)
    # x = 3: units 3 and -3 -> 3 + 0.01 (-3); a ReLU would give 3.
    np.testing.assert_allclose(mlp(jnp.array([[3.0], [-2.0]])), [[2.97], [1.98]], rtol=1e-6)


def pytorch_gru_step(h, x, w_ih, w_hh, b_ih, b_hh):
    """nn.GRUCell's documented update in NumPy, with PyTorch's (3H, in) weights and two biases."""
    sigmoid = lambda v: 1.0 / (1.0 + np.exp(-v))  # noqa: E731
    gi, gh = x @ w_ih.T + b_ih, h @ w_hh.T + b_hh
    i_r, i_z, i_n = np.split(gi, 3, axis=-1)
    h_r, h_z, h_n = np.split(gh, 3, axis=-1)
    r, z = sigmoid(i_r + h_r), sigmoid(i_z + h_z)
    n = np.tanh(i_n + r * h_n)  # h_n holds b_hn: the hidden bias sits inside the reset product
    return (1.0 - z) * n + z * h


def test_gru_cell_is_pytorchs_with_b_hn_inside_the_reset_product():
    hidden, inputs = 6, 5
    cell = dynamics.GRUCell(inputs, hidden, rngs=nnx.Rngs(3))
    rng = np.random.default_rng(0)
    h = rng.normal(size=(4, hidden)).astype(np.float32)
    x = rng.normal(size=(4, inputs)).astype(np.float32)
    w_ih = np.asarray(cell.input_kernel[...]).T
    w_hh = np.asarray(cell.hidden_kernel[...]).T
    # PyTorch's bias_ih / bias_hh, each of 3H: [b_ir, b_iz, b_in] and [b_hr, b_hz, b_hn].
    assert cell.input_bias.shape == cell.hidden_bias.shape == (3 * hidden,)
    b_ih, b_hh = np.asarray(cell.input_bias[...]), np.asarray(cell.hidden_bias[...])
    expected = pytorch_gru_step(h, x, w_ih, w_hh, b_ih, b_hh)
    np.testing.assert_allclose(cell(jnp.asarray(h), jnp.asarray(x)), expected, atol=1e-6)

    # Hand case: z = 0 (h' = n) and r = 0 leave n = tanh(W_in x + b_in), whatever W_hn and b_hn.
    gates = np.asarray(cell.input_bias[...]).copy()
    gates[: 2 * hidden] = -200.0  # sigmoid(-200) is 0 in float32
    cell.input_bias[...] = jnp.asarray(gates)
    cell.hidden_bias[...] = jnp.asarray(np.r_[np.zeros(2 * hidden), b_hh[2 * hidden :]])
    w_in, b_n = w_ih[2 * hidden :], gates[2 * hidden :]
    np.testing.assert_allclose(
        cell(jnp.asarray(h), jnp.asarray(x)), np.tanh(x @ w_in.T + b_n), atol=1e-6
    )
    # r = 1: b_hn is added to W_hn h inside the tanh.
    gates[:hidden] = 200.0
    cell.input_bias[...] = jnp.asarray(gates)
    cell.hidden_bias[...] = jnp.asarray(np.r_[np.zeros(2 * hidden), np.full(hidden, 0.5)])
    w_hn = w_hh[2 * hidden :]
    np.testing.assert_allclose(
        cell(jnp.asarray(h), jnp.asarray(x)),
        np.tanh(x @ w_in.T + b_n + h @ w_hn.T + 0.5),
        atol=1e-6,
    )


def test_an_untrained_rotation_decoder_starts_at_random_rotations_as_released():
    """The 6D vector is the decoder's output itself (no identity shift): untrained, the joints'
    rotations are its random bias's, far from the identity (shifted by the identity's 6D vector
    they would lie within about 25 degrees of it: the bias is below 1/sqrt(mlp) = 0.18)."""
    model = Dynamics(DynamicsConfig(latent=8, hidden=16, mlp=32), *chain(K), rngs=nnx.Rngs(5))
    h, z = jnp.zeros((1, 16)), jnp.zeros((1, 8))
    _, rotations = model.decode(h, z, jnp.ones((1, K)))
    d6 = model.rotation_decoder(jnp.concatenate([h, z], -1)).reshape(1, K, 6)
    np.testing.assert_allclose(rotations, geometry.rotation_6d_to_matrix(d6), atol=1e-6)
    cos = (np.trace(np.asarray(rotations[0]), axis1=-2, axis2=-1) - 1) / 2
    angles = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    assert np.median(angles) > 45, angles


def test_gru_cell_runs_under_nnx_scan():
    cell = dynamics.GRUCell(3, 4, rngs=nnx.Rngs(1))
    xs = jax.random.normal(jax.random.key(0), (5, 2, 3))  # (T, B, in)
    h0 = jnp.zeros((2, 4))

    @nnx.scan(in_axes=(None, nnx.Carry, 0), out_axes=(nnx.Carry, 0))
    def run(cell, h, x):
        h = cell(h, x)
        return h, h

    _, hs = run(cell, h0, xs)
    h, expected = h0, []
    for x in xs:
        h = cell(h, x)
        expected.append(h)
    np.testing.assert_allclose(hs, np.stack(expected), atol=1e-6)


def test_bone_lengths_take_the_lower_middle_value_for_even_frame_counts():
    x = np.zeros((4, 2, 3), np.float32)  # joint 1 hangs from joint 0 at distances 3, 1, 10, 2
    x[:, 1, 0] = [3.0, 1.0, 10.0, 2.0]
    lengths = np.asarray(bone_lengths(jnp.asarray(x), (0, 0)))
    np.testing.assert_array_equal(lengths, [0.0, 2.0])  # torch.median: 2, jnp.median: 2.5
    np.testing.assert_array_equal(dynamics.lower_median(jnp.array([4.0, 1.0, 3.0])), 3.0)


def chain(k: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
    return tuple(max(j - 1, 0) for j in range(k)), tuple(range(k))


def test_trainable_parameter_count_is_the_releases():
    """K = 8, D_z 128, D_h 512: the release's dynamics module holds 1,408,979 values, of which 24
    are the frozen offset directions; the GRU keeps PyTorch's two bias vectors."""
    model = Dynamics(DynamicsConfig(), *chain(8), rngs=nnx.Rngs(0))
    count = sum(x.size for x in jax.tree.leaves(nnx.state(model, nnx.Param)))
    assert count == 1_408_979 - 24 == 1_408_955
    assert model.rnn.input_bias.shape == model.rnn.hidden_bias.shape == (3 * 512,)
    assert sum(x.size for x in jax.tree.leaves(nnx.state(model, Buffer))) == 24


def test_initialisation_is_pytorchs_default():
    model = Dynamics(DynamicsConfig(latent=32, hidden=128, mlp=64), *chain(8), rngs=nnx.Rngs(2))
    for name in ("posterior", "prior", "global_decoder", "rotation_decoder"):
        for layer in (getattr(model, name).hidden, getattr(model, name).out):
            bound = 1.0 / np.sqrt(layer.kernel.shape[0])  # 1/sqrt(fan_in) for weight and bias
            for values in (np.asarray(layer.kernel[...]), np.asarray(layer.bias[...])):
                assert np.abs(values).max() <= bound
            kernel = np.asarray(layer.kernel[...])
            np.testing.assert_allclose(kernel.std(), bound / np.sqrt(3), rtol=0.1)  # uniform
    rnn, bound = model.rnn, 1.0 / np.sqrt(128)
    for values in (
        rnn.input_kernel[...],
        rnn.hidden_kernel[...],
        rnn.input_bias[...],
        rnn.hidden_bias[...],
    ):
        values = np.asarray(values)
        assert np.abs(values).max() <= bound and values.std() > 0.9 * bound / np.sqrt(3)


def test_initial_hidden_state_starts_unit_normal():
    model = Dynamics(DynamicsConfig(), *chain(8), rngs=nnx.Rngs(0))
    h0 = np.asarray(model.initial_hidden[...])
    assert h0.shape == (512,) and 0.8 <= h0.std() <= 1.2 and abs(h0.mean()) < 0.15
    assert isinstance(model.initial_hidden, nnx.Param)  # learned
    again = Dynamics(DynamicsConfig(), *chain(8), rngs=nnx.Rngs(0)).initial_hidden[...]
    np.testing.assert_array_equal(h0, again)  # the run's seed fixes it
