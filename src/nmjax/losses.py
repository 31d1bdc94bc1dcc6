"""Every loss term of Neural Marionette (paper Eqs. 3, 4, 8-17, 23; docs/architecture.md §5).

Pure functions of arrays; each works under `jax.jit`, `jax.vmap` and `jax.grad`. Shapes use B
batch, T frames, G voxel grid, g heatmap grid, K keypoints, N decomposed affinity matrices.
Keypoints are `(..., K, 4)`: xyz in the normalised cube, intensity alpha last. Where the printed
formula and the released implementation differ, the default follows the released implementation
(it produced the published tables) and the docstring says so.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
from jax import Array

# Eq. 12 lives with the keypoint maps (the detector needs it without the losses); re-exported
# because the graph terms below are stated on its output.
from nmjax.keypoints import affinity_from_params as affinity_from_params
from nmjax.keypoints import coord_grid, influence

if TYPE_CHECKING:
    from nmjax.config import LossWeights

BCE_EPS = 1e-7  # probabilities are clipped to [eps, 1 - eps] before the logarithm
COS_EPS = 1e-6  # cosine similarity: each norm is clamped to at least this

TERMS = ("recon", "sparse", "sep", "vol", "local", "time", "complex", "traj")


def _safe_norm(x: Array, axis: int = -1) -> Array:
    """Euclidean norm whose gradient at 0 is 0 instead of NaN."""
    sq = jnp.sum(jnp.square(x), axis=axis)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def _pairwise_sq_dist(mu: Array) -> Array:
    """(..., K, 3) -> (..., K, K) squared Euclidean distances (exact differences, smooth)."""
    diff = mu[..., :, None, :] - mu[..., None, :, :]
    return jnp.sum(jnp.square(diff), axis=-1)


# --- keypoint detector (Eqs. 8-11) -------------------------------------------------------------


def reconstruction_bce(voxels: Array, recon: Array) -> Array:
    """Eq. 9: binary cross-entropy between occupancy and reconstruction, mean over voxels.

    Args:
        voxels: (..., G, G, G) occupancy in {0, 1} (soft targets allowed).
        recon: (..., G, G, G) reconstructed occupancy probabilities in [0, 1].

    Returns:
        (...) one value per frame (e.g. (B, T)); Eq. 9's 1/T sum is the caller's mean. `recon` is
        clipped to [1e-7, 1 - 1e-7] so that the loss and its gradient stay finite.
    """
    p = jnp.clip(recon, BCE_EPS, 1.0 - BCE_EPS)
    bce = -(voxels * jnp.log(p) + (1.0 - voxels) * jnp.log1p(-p))
    return jnp.mean(bce, axis=(-3, -2, -1))


def heatmap_sparsity(heatmaps: Array) -> Array:
    """Eq. 10: mean over K of |mean over the grid of heatmap k|.

    The printed ||m_k,t|| is the L1 norm; the released code uses the grid mean (the L1 norm
    divided by g^3 for the non-negative heatmaps), which this computes.

    Args:
        heatmaps: (..., g, g, g, K).

    Returns:
        (...) one value per frame.
    """
    return jnp.mean(jnp.abs(jnp.mean(heatmaps, axis=(-4, -3, -2))), axis=-1)


def separation(keypoints: Array, sigma: float = 0.02, *, per_frame: bool = False) -> Array:
    """Eq. 11: penalises keypoints whose centred trajectories coincide.

    s_k,t = mu_k,t - mean_t mu_k,t; d_kk' = mean_t ||s_k,t - s_k',t||^2;
    loss = sum_{k != k'} exp(-d_kk' / (2 sigma^2)) / (K (K - 1)), with sigma_s = 1 / (2 sigma^2)
    (sigma = 0.02 gives the paper's sigma_s = 1250). The printed Eq. 11 takes the exponential per
    frame and then the time mean; the released code (and Minderer et al. 2019) average the
    distance over time first, which is the default. `per_frame=True` computes the printed form.

    Args:
        keypoints: (..., T, K, 4) one trajectory per leading index (e.g. (B, T, K, 4)).
        sigma: width of the kernel, in normalised units.
        per_frame: exponential inside the time mean (Eq. 11 as printed).

    Returns:
        (...) one value per sequence (e.g. (B,)); 1 when all trajectories are identical.
    """
    mu = keypoints[..., :3]
    s = mu - jnp.mean(mu, axis=-3, keepdims=True)  # (..., T, K, 3)
    d = _pairwise_sq_dist(s)  # (..., T, K, K)
    if per_frame:
        e = jnp.mean(jnp.exp(-d / (2 * sigma**2)), axis=-3)
    else:
        e = jnp.exp(-jnp.mean(d, axis=-3) / (2 * sigma**2))  # (..., K, K)
    k = keypoints.shape[-2]
    off_diagonal = 1.0 - jnp.eye(k, dtype=e.dtype)
    return jnp.sum(e * off_diagonal, axis=(-2, -1)) / max(k * (k - 1), 1)  # K = 1: no pairs, 0


def _nearest_keypoint(sq: Array) -> Array:
    """(K, P) -> (P,) index of the smallest row per column (first on ties).

    A scan over the K rows with a running (min, index) pair: on XLA's CPU backend this is about
    twice as fast as `jnp.argmin`, whose variadic reduction is slow.
    """

    def step(carry, row_and_k):
        best, index = carry
        row, k = row_and_k
        better = row < best
        return (jnp.where(better, row, best), jnp.where(better, k, index)), None

    k = sq.shape[0]
    init = (jnp.full(sq.shape[1:], jnp.inf, sq.dtype), jnp.zeros(sq.shape[1:], jnp.int32))
    (_, index), _ = jax.lax.scan(step, init, (sq, jnp.arange(k, dtype=jnp.int32)))
    return index


def _volume_frame(occupancy: Array, mu: Array, points: Array) -> Array:
    """One frame of Eq. 8: occupancy (P,), mu (K, 3), cells (P, 3) -> scalar."""
    # Nearest keypoint of every cell from |mu|^2 - 2 mu.p (+ |p|^2, which does not change the
    # argmin): a (K, P) matrix, never (K, P, 3). The index is piecewise constant, so it carries
    # no gradient; the exact squared distance to that keypoint is then recomputed, and the
    # backward pass keeps only the (P,) indices instead of the (K, P) matrix.
    fixed = jax.lax.stop_gradient(mu)
    cross = jnp.matmul(fixed, points.T, precision=jax.lax.Precision.HIGHEST)  # no TF32 on GPU
    sq = jnp.sum(jnp.square(fixed), axis=-1)[:, None] - 2.0 * cross
    nearest = _nearest_keypoint(sq)  # (P,)
    dist = jnp.sum(jnp.square(points - mu[nearest]), axis=-1)  # (P,)
    return jnp.sum(occupancy * dist) / jnp.maximum(jnp.sum(occupancy), 1.0)


def volume_fitting(voxels: Array, keypoints: Array) -> Array:
    """Eq. 8: one-directional Chamfer distance from the occupied voxels to the keypoints.

    For every occupied cell p (coordinates from `coord_grid(G)`), min_k ||p - mu_k||^2, averaged
    over the occupied cells of the frame (0 for an empty frame; the count is clamped to >= 1).
    Memory stays O(G^3 K) for one frame at a time: frames go through `lax.map`, and the backward
    pass keeps only each cell's nearest-keypoint index (G^3 integers per frame). Where several
    keypoints tie for nearest, the whole gradient goes to the first of them (a valid
    subgradient of the min).

    Args:
        voxels: (..., G, G, G) occupancy (weights; normally 0/1).
        keypoints: (..., K, 4) with the same leading shape (e.g. (B, T)).

    Returns:
        (...) one value per frame.
    """
    lead = voxels.shape[:-3]
    if keypoints.shape[:-2] != lead:
        raise ValueError(
            f"volume_fitting: voxels {voxels.shape} and keypoints {keypoints.shape} must share "
            "their leading (batch, time) axes"
        )
    g = voxels.shape[-1]
    occ = voxels.reshape(-1, g**3).astype(jnp.float32)
    mu = keypoints[..., :3].reshape(-1, keypoints.shape[-2], 3)
    points = coord_grid(g).reshape(-1, 3)
    out = jax.lax.map(lambda args: _volume_frame(*args, points), (occ, mu))
    return out.reshape(lead)


# --- affinity (Eqs. 12-17) ---------------------------------------------------------------------


def graph_local(keypoints: Array, affinity: Array, intensity_weighted: bool = False) -> Array:
    """Eq. 15: affinity-weighted squared distances between keypoints.

    l_t,kk' = ||mu_k,t - mu_k',t||^2; loss = mean over (k, k') of a_kk' l_t,kk' (times alpha_k,t
    when `intensity_weighted`, as printed; the released training uses the unweighted form).

    Args:
        keypoints: (..., K, 4), e.g. (B, T, K, 4).
        affinity: (N, K, K) decomposed affinities (combined with max over N, Eq. 12) or (K, K).
        intensity_weighted: multiply row k by alpha_k,t (Eq. 15 as printed).

    Returns:
        (...) one value per frame.
    """
    a = influence(affinity)
    terms = a * _pairwise_sq_dist(keypoints[..., :3])
    if intensity_weighted:
        terms = terms * keypoints[..., :, 3:4]
    return jnp.mean(terms, axis=(-2, -1))


def graph_time(keypoints: Array, affinity: Array, intensity_weighted: bool = False) -> Array:
    """Eq. 16: affinity-weighted change of the pairwise distances over time.

    As `graph_local` with |l_t,kk' - mean_t l_t,kk'| in place of l_t,kk' (the printed Eq. 16 omits
    the absolute value, with which the loss would be identically zero).

    Args:
        keypoints: (..., T, K, 4), e.g. (B, T, K, 4).
        affinity: (N, K, K) or (K, K).
        intensity_weighted: multiply row k by alpha_k,t (Eq. 16 as printed).

    Returns:
        (..., T) one value per frame.
    """
    a = influence(affinity)
    dist = _pairwise_sq_dist(keypoints[..., :3])  # (..., T, K, K)
    terms = a * jnp.abs(dist - jnp.mean(dist, axis=-3, keepdims=True))
    if intensity_weighted:
        terms = terms * keypoints[..., :, 3:4]
    return jnp.mean(terms, axis=(-2, -1))


def graph_complexity(affinity: Array) -> Array:
    """Eq. 17: overlap between the decomposed affinity matrices.

    sum_n sum_{n' != n} of the squared entries of A_n * A_n', averaged over the K x K entries
    (the released code squares the Frobenius norm of the printed formula and takes the mean).
    Computed as ((sum_n A_n^2)^2 - sum_n A_n^4), which is O(N K^2).

    Args:
        affinity: (N, K, K).

    Returns:
        scalar; 0 when the A_n have disjoint supports.
    """
    sq = jnp.square(affinity)
    cross = jnp.square(jnp.sum(sq, axis=0)) - jnp.sum(jnp.square(sq), axis=0)
    return jnp.mean(cross)


def _clamped_norm(x: Array) -> Array:
    """(..., 3) -> (...) the norm clamped to at least COS_EPS in value only: the gradient is the
    unclamped norm's, as in PyTorch's cosine similarity (which clamps the norm in place outside
    autograd; the release's L_traj is computed with it)."""
    norm = _safe_norm(x)
    return norm + jax.lax.stop_gradient(jnp.maximum(norm, COS_EPS) - norm)


def _cosine(u: Array, v: Array) -> Array:
    """(..., K, 3) x (..., K, 3) -> (..., K, K) cosine similarity, norms clamped to COS_EPS."""
    nu = _clamped_norm(u)
    nv = _clamped_norm(v)
    return jnp.einsum("...kd,...ld->...kl", u / nu[..., None], v / nv[..., None])


def trajectory_cost(
    keypoints: Array, intensity_weighted: bool = False, printed_scale: bool = False
) -> Array:
    """Eq. 14's cost C(mu_k, mu_k'), averaged over the batch and time.

    vel_t = mu_t+1 - mu_t, acc_t = vel_t+1 - vel_t (finite differences over T);
    C = (1 - cos(vel_k, vel_k')) / 2 + (1 - cos(acc_k, acc_k')) / 2, in [0, 2],
    each cosine averaged over its own frames (and every leading axis). That is the released
    code's cost (docs/architecture.md §5), on which the per-dataset w_traj of Tables 4-8 were tuned;
    the default. `printed_scale=True` gives the printed Eq. 14's [0, 1] scale (the same cost
    halved). The printed Eq. 14 divides each inner product by its own absolute value (a sign); the
    released code uses the cosine similarity, computed here as PyTorch computes it: both norms
    clamped to 1e-6 in value, the gradient the unclamped norm's (a zero velocity gives cosine
    0). With `intensity_weighted`, row k is weighted by alpha_k averaged onto the velocity frames
    ((alpha_t + alpha_t+1) / 2) and onto the acceleration frames (mean of the two velocity-frame
    weights).

    Args:
        keypoints: (..., T, K, 4) with T >= 3.
        intensity_weighted: weight row k by the (frame-averaged) alpha_k (Eq. 13 as printed).
        printed_scale: halve the cost (the printed Eq. 14's range [0, 1]).

    Returns:
        (K, K): 0 for parallel motion, 2 (1 with `printed_scale`) for opposite motion
        (velocities and accelerations).
    """
    if keypoints.shape[-3] < 3:
        raise ValueError(
            f"graph_trajectory needs at least 3 frames for accelerations, got {keypoints.shape}"
        )
    mu = keypoints[..., :3]
    vel = mu[..., 1:, :, :] - mu[..., :-1, :, :]
    acc = vel[..., 1:, :, :] - vel[..., :-1, :, :]
    divisor = 4.0 if printed_scale else 2.0
    c_vel = (1.0 - _cosine(vel, vel)) / divisor  # (..., T-1, K, K)
    c_acc = (1.0 - _cosine(acc, acc)) / divisor  # (..., T-2, K, K)
    if intensity_weighted:
        alpha = keypoints[..., 3]
        w_vel = (alpha[..., 1:, :] + alpha[..., :-1, :]) / 2
        w_acc = (w_vel[..., 1:, :] + w_vel[..., :-1, :]) / 2
        c_vel = c_vel * w_vel[..., :, None]
        c_acc = c_acc * w_acc[..., :, None]
    k = keypoints.shape[-2]
    return jnp.mean(c_vel.reshape(-1, k, k), axis=0) + jnp.mean(c_acc.reshape(-1, k, k), axis=0)


def graph_trajectory(
    keypoints: Array,
    affinity: Array,
    intensity_weighted: bool = False,
    printed_scale: bool = False,
) -> Array:
    """Eq. 13: affinity-weighted trajectory dissimilarity, mean over (k, k') of a_kk' C_kk'.

    See `trajectory_cost` for C (averaged over batch and time first, as in the released code;
    by default on the released [0, 2] scale).

    Args:
        keypoints: (..., T, K, 4), e.g. (B, T, K, 4), T >= 3.
        affinity: (N, K, K) or (K, K).
        intensity_weighted: weight by alpha_k (Eq. 13 as printed).
        printed_scale: C on the printed Eq. 14's [0, 1] scale.

    Returns:
        scalar.
    """
    cost = trajectory_cost(keypoints, intensity_weighted, printed_scale)
    return jnp.mean(influence(affinity) * cost)


# --- dynamics (Eqs. 3-4) -----------------------------------------------------------------------


def vrnn_reconstruction(x: Array, x_hat: Array, feature_axes: int = 2) -> Array:
    """Eq. 3: squared error summed over each frame's features, mean over the other axes.

    Args:
        x: (B, T, K, 4) observed keypoints (or (B, T, 4K) with `feature_axes=1`).
        x_hat: reconstruction, same shape.
        feature_axes: how many trailing axes form one frame's vector x_t.

    Returns:
        scalar: mean over (B, T) of ||x_t - x_hat_t||^2.
    """
    if x.shape != x_hat.shape:
        raise ValueError(f"vrnn_reconstruction: x {x.shape} and x_hat {x_hat.shape} differ")
    sq = jnp.sum(jnp.square(x - x_hat), axis=tuple(range(-feature_axes, 0)))
    return jnp.mean(sq)


def kl_diag_gaussians(
    mean_q: Array, std_q: Array, mean_p: Array, std_p: Array, axis: int | None = -1
) -> Array:
    """Eq. 4's KL(q || p) between diagonal Gaussians, in closed form.

    KL = log(std_p / std_q) + (std_q^2 + (mean_q - mean_p)^2) / (2 std_p^2) - 1/2 per dimension.

    Args:
        mean_q, std_q: (..., D) posterior mean and standard deviation (std > 0).
        mean_p, std_p: (..., D) prior mean and standard deviation (std > 0).
        axis: summed axis (the latent dimension, default last); None returns per-dimension values.

    Returns:
        (...) KL per distribution, or (..., D) with `axis=None`. The phase-2 loss
        (`nmjax.train.dyn.loss_fn`) takes the per-dimension values and averages them over batch,
        time and dimension, as the authors' release reduces Eq. 4.
    """
    var_ratio = jnp.square(std_q / std_p)
    mahal = jnp.square((mean_q - mean_p) / std_p)
    kl = 0.5 * (var_ratio + mahal - 1.0 - jnp.log(var_ratio))
    return kl if axis is None else jnp.sum(kl, axis=axis)


def joint_supervision(keypoints: Array, joints: Array) -> Array:
    """Ground-truth-supervised replacement of L_vol (paper Sec. 5, the "GT" row of Table 2).

    Mean squared distance between keypoint k and ground-truth joint k.

    Args:
        keypoints: (..., K, 4) keypoints (xyz used).
        joints: (..., K, 3) ground-truth joints in the same normalised frame, one per keypoint.

    Returns:
        (...) mean over K of ||mu_k - j_k||^2.
    """
    if keypoints.shape[-2] != joints.shape[-2]:
        raise ValueError(
            f"joint supervision needs one ground-truth joint per keypoint: K="
            f"{keypoints.shape[-2]} keypoints but J={joints.shape[-2]} joints; set "
            f"model.num_keypoints={joints.shape[-2]}"
        )
    return jnp.mean(jnp.sum(jnp.square(keypoints[..., :3] - joints), axis=-1), axis=-1)


# --- total (Eq. 23) ----------------------------------------------------------------------------


def _volume_term(outputs: dict[str, Array], target: str) -> Array:
    """L_vol (Eq. 8), or with target "joints" the ground-truth-supervised baseline."""
    if target == "volume":
        return volume_fitting(outputs["voxels"], outputs["keypoints"])
    if target == "joints":
        if "joints" not in outputs:
            raise ValueError(
                "weights.vol_target='joints' needs ground-truth joints in outputs['joints']; "
                "use a dataset with joints"
            )
        return joint_supervision(outputs["keypoints"], outputs["joints"])
    raise ValueError(f"weights.vol_target must be 'volume' or 'joints', got {target!r}")


def skeleton_loss(
    outputs: dict[str, Array], weights: LossWeights
) -> tuple[Array, dict[str, Array]]:
    """Eq. 23: the weighted sum of the eight phase-1 terms.

    Args:
        outputs: {"voxels": (B, T, G, G, G) occupancy, "recon": (B, T, G, G, G) probabilities,
            "heatmaps": (B, T, g, g, g, K), "keypoints": (B, T, K, 4),
            "affinity": (N, K, K) (e.g. from `keypoints.affinity_from_params`)}.
        weights: `nmjax.config.LossWeights` (weights, sep_sigma, intensity_weighted).

    Returns:
        (total, terms): scalar total and the unweighted scalar value of each term, keyed
        recon, sparse, sep, vol, local, time, complex, traj (each averaged over batch and time).
    """
    missing = {"voxels", "recon", "heatmaps", "keypoints", "affinity"} - set(outputs)
    if missing:
        raise ValueError(f"skeleton_loss: outputs lacks {sorted(missing)}")
    voxels, kp, aff = outputs["voxels"], outputs["keypoints"], outputs["affinity"]
    iw = weights.intensity_weighted
    terms = {
        "recon": jnp.mean(reconstruction_bce(voxels, outputs["recon"])),
        "sparse": jnp.mean(heatmap_sparsity(outputs["heatmaps"])),
        "sep": jnp.mean(separation(kp, weights.sep_sigma)),
        "vol": jnp.mean(_volume_term(outputs, weights.vol_target)),
        "local": jnp.mean(graph_local(kp, aff, iw)),
        "time": jnp.mean(graph_time(kp, aff, iw)),
        "complex": graph_complexity(aff),
        "traj": graph_trajectory(kp, aff, iw),
    }
    total = sum(getattr(weights, name) * value for name, value in terms.items())
    return total, terms
