import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nmjax import keypoints as kpm

SETTINGS = settings(max_examples=15, deadline=None)


def test_coord_grid_ij_order():
    grid = np.asarray(kpm.coord_grid(4))
    x = np.linspace(-1, 1, 4)
    assert grid.shape == (4, 4, 4, 3)
    np.testing.assert_allclose(grid[2, 0, 3], [x[2], x[0], x[3]], atol=1e-6)
    np.testing.assert_allclose(grid[:, 1, 1, 0], x, atol=1e-6)


def test_add_coord_channels():
    x = jnp.ones((2, 3, 5, 5, 5, 2))
    out = kpm.add_coord_channels(x)
    assert out.shape == (2, 3, 5, 5, 5, 5)
    np.testing.assert_allclose(out[1, 2, ..., 2:], kpm.coord_grid(5), atol=1e-6)
    np.testing.assert_allclose(out[..., :2], 1.0)
    with pytest.raises(ValueError, match="n, n, n, C"):
        kpm.add_coord_channels(jnp.ones((4, 5, 5, 2)))


def test_delta_heatmap_gives_cell_coordinate():
    g, k = 6, 3
    cells = [(0, 5, 2), (3, 3, 1), (5, 0, 4)]
    heat = np.zeros((g, g, g, k), np.float32)
    for i, c in enumerate(cells):
        heat[c + (i,)] = 200.0 if i == 0 else 100.0
    kp = np.asarray(kpm.heatmap_to_keypoints(jnp.asarray(heat)))
    x = np.linspace(-1, 1, g)
    for i, c in enumerate(cells):
        np.testing.assert_allclose(kp[i, :3], x[list(c)], atol=1e-5)
    # alpha: mean / max mean -> 1 for the strongest, 0.5 for the others.
    np.testing.assert_allclose(kp[:, 3], [1.0, 0.5, 0.5], atol=1e-5)


def test_a_near_zero_heatmap_puts_its_keypoint_near_the_grid_centre():
    # The release adds 1e-6 to every cell before normalising. On a 4^3 grid a heatmap of 1e-6 in
    # cell (0, 0, 0) and 0 elsewhere gives, per axis, marginal 17e-6 at x = -1 and 16e-6 at
    # -1/3, 1/3 and 1 (total 65e-6): mu = (-17 - 16/3 + 16/3 + 16) / 65 = -1/65 on each axis.
    # (1e-6 added once to the denominator instead would give -1/2.) Zeros: exactly the centre.
    g = 4
    heat = np.zeros((g, g, g, 2), np.float32)
    heat[0, 0, 0, 0] = 1e-6
    kp = np.asarray(kpm.heatmap_to_keypoints(jnp.asarray(heat)))
    np.testing.assert_allclose(kp[0, :3], -1 / 65, rtol=1e-4)
    np.testing.assert_allclose(kp[1, :3], 0.0, atol=1e-7)


def _numpy_keypoints(heat):
    g = heat.shape[-2]
    x = np.linspace(-1, 1, g)
    mean = heat.mean(axis=(-4, -3, -2))
    alpha = mean / (mean.max(axis=-1, keepdims=True) + 1e-6)
    mu = []
    for others in ((-3, -2), (-4, -2), (-4, -3)):
        m = (heat + 1e-6).sum(axis=others)  # the release's 1e-6 in every cell
        p = m / m.sum(axis=-2, keepdims=True)
        mu.append((p * x[:, None]).sum(axis=-2))
    return np.stack([*mu, alpha], axis=-1)


@SETTINGS
@given(
    batch=st.sampled_from([1, 3]),
    g=st.sampled_from([2, 5]),
    k=st.sampled_from([1, 4]),
    seed=st.integers(0, 2**16),
)
def test_heatmap_to_keypoints_matches_numpy(batch, g, k, seed):
    heat = np.random.default_rng(seed).random((batch, g, g, g, k)).astype(np.float32)
    got = jax.jit(kpm.heatmap_to_keypoints)(jnp.asarray(heat))
    np.testing.assert_allclose(got, _numpy_keypoints(heat), rtol=1e-4, atol=1e-5)
    assert np.all((got[..., :3] >= -1 - 1e-5) & (got[..., :3] <= 1 + 1e-5))


@SETTINGS
@given(
    n=st.sampled_from([2, 7]),
    k=st.sampled_from([1, 3]),
    sigma=st.floats(0.5, 2.0),
    seed=st.integers(0, 99),
)
def test_gaussian_maps_matches_numpy(n, k, sigma, seed):
    rng = np.random.default_rng(seed)
    kp = np.concatenate([rng.uniform(-1, 1, (2, k, 3)), rng.uniform(0, 1, (2, k, 1))], -1)
    kp = kp.astype(np.float32)
    got = np.asarray(jax.jit(kpm.gaussian_maps, static_argnums=2)(jnp.asarray(kp), sigma, n))
    grid = np.stack(np.meshgrid(*[np.linspace(-1, 1, n)] * 3, indexing="ij"), -1)
    d2 = ((grid[None, :, :, :, None, :] - kp[:, None, None, None, :, :3]) ** 2).sum(-1)
    want = kp[:, None, None, None, :, 3] * np.exp(-d2 / (2 * (sigma / n) ** 2))
    assert got.shape == (2, n, n, n, k)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6)


def test_gaussian_map_peak_and_round_trip():
    n = 9
    x = np.linspace(-1, 1, n)
    kp = jnp.array([[x[2], x[6], x[4], 0.7]], jnp.float32)
    maps = kpm.gaussian_maps(kp, 1.0, n)
    assert np.unravel_index(np.argmax(maps[..., 0]), (n, n, n)) == (2, 6, 4)
    np.testing.assert_allclose(maps.max(), 0.7, rtol=1e-6)
    back = kpm.heatmap_to_keypoints(maps)
    # The release's 1e-6 per cell adds n^3 1e-6 of mass centred on 0: mu shrinks by M / (M + that).
    mass = float(jnp.sum(maps))
    np.testing.assert_allclose(back[0, :3], kp[0, :3] * mass / (mass + n**3 * 1e-6), atol=1e-5)


def test_gradients_finite():
    heat = jax.random.uniform(jax.random.key(0), (2, 4, 4, 4, 3))

    def f(h):
        kp = kpm.heatmap_to_keypoints(h)
        return jnp.sum(kpm.gaussian_maps(kp, 1.5, 4) ** 2)

    grad = jax.jit(jax.grad(f))
    assert np.all(np.isfinite(grad(heat)))
    g0 = grad(jnp.zeros_like(heat))  # all-zero heatmaps: the eps guards keep it finite
    assert np.all(np.isfinite(g0))


def test_heatmap_far_mass_counts_the_mass_beyond_the_radius():
    g, k = 6, 2
    heat = np.zeros((1, g, g, g, k), np.float32)
    heat[0, 2, 2, 2, 0] = 5.0  # keypoint 0: the peak, one neighbour (1 cell), a far cell (3 cells)
    heat[0, 2, 2, 3, 0] = 2.0
    heat[0, 2, 5, 2, 0] = 3.0
    heat[0, 1, 1, 1, 1] = 1.0  # keypoint 1: one cell, nothing far
    far = np.asarray(kpm.heatmap_far_mass(jnp.asarray(heat), radius=1.5))
    assert far.shape == (1, k)
    np.testing.assert_allclose(far[0], [3.0 / 10.0, 0.0], rtol=1e-5)
    # A uniform heatmap peaks at its first cell, a corner: 7 cells lie within 1.5 of it.
    uniform = np.asarray(kpm.heatmap_far_mass(jnp.ones((g, g, g, 1)), radius=1.5))
    np.testing.assert_allclose(uniform, [1.0 - 7.0 / 216.0], rtol=1e-5)


def test_keypoint_temperature_is_a_spatial_softmax_of_the_log_heatmap():
    rng = np.random.default_rng(0)
    g, k, tau = 5, 3, 0.5
    z = rng.normal(size=(2, g, g, g, k)) * 2.0
    kp = np.asarray(kpm.heatmap_to_keypoints(jnp.asarray(np.exp(z), jnp.float32), tau))
    p = np.exp(z / tau)
    p /= p.sum(axis=(1, 2, 3), keepdims=True)
    grid = np.asarray(kpm.coord_grid(g), np.float64)  # (g, g, g, 3)
    want = np.einsum("bxyzk,xyzd->bkd", p, grid)
    np.testing.assert_allclose(kp[..., :3], want, atol=1e-4)
    # alpha does not depend on the temperature.
    plain = np.asarray(kpm.heatmap_to_keypoints(jnp.asarray(np.exp(z), jnp.float32)))
    np.testing.assert_allclose(kp[..., 3], plain[..., 3], rtol=1e-6)


def test_low_temperature_pulls_mu_from_the_floor_to_the_peak():
    g = 8
    heat = np.full((g, g, g, 1), 0.05, np.float32)  # a softplus-like floor everywhere ...
    heat[1, 1, 1, 0] = 1.0  # ... and a peak in a corner
    peak = np.asarray(kpm.coord_grid(g))[1, 1, 1]
    far = [
        np.linalg.norm(np.asarray(kpm.heatmap_to_keypoints(jnp.asarray(heat), t))[0, :3] - peak)
        for t in (1.0, 0.5, 0.25)
    ]
    assert far[0] > 0.5 and far[0] > far[1] > far[2] and far[2] < 0.05
    with pytest.raises(ValueError, match="temperature"):
        kpm.heatmap_to_keypoints(jnp.asarray(heat), 0.0)
