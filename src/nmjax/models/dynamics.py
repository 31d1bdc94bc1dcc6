"""Dynamics module (paper Sec. 3-4, appendix Fig. 10-11; docs/architecture.md §8).

A variational RNN over keypoint trajectories x_{1:T} (B,T,K,4). At every step the posterior
q(z_t | h_t, x_t) and the prior p(z_t | h_t) are diagonal Gaussians; a decoder turns (h_t, z_t)
into the reconstruction x_hat_t; a GRU consumes [x_hat_t, z_t] to produce h_{t+1}.

Two decoders share the cell:

- "nm" (Neural Marionette): a global pose decoder gives the root position and the intensities
  (Eq. 18), a rotation decoder gives one local rotation per joint in the 6D representation
  (Eq. 19), and forward kinematics along the extracted skeleton (Eq. 2) turns them into joint
  positions. Offsets are fixed random unit directions (drawn once at initialisation, never trained)
  scaled by bone lengths measured on the observed sequence (Eq. 20).
- "vrnn" (baseline of Chung et al. / Minderer et al.): the decoder regresses the 4K keypoint values
  directly.

Every choice the paper leaves open is the authors' release's (compared weight for weight,
docs/architecture.md §8): LeakyReLU (slope 0.01) in every MLP, PyTorch's GRU cell (`GRUCell`, the
hidden bias b_hn inside the reset product), bone lengths as torch's median (the lower middle value),
a learned initial hidden state drawn N(0, 1), and PyTorch's default initialisation of every Linear
and of the GRU (`torch_uniform`). The phase-2 loss reduces the KL as the release does
(`nmjax.train.dyn.loss_fn`).

The recurrence runs under `jax.lax.scan` with one key per step split up front. The S posterior
samples of the best-of-S training rule are decoded together as one extra leading axis (the
computation `jax.vmap` would produce); forward kinematics always sees one flattened batch axis,
because XLA:CPU of jax 0.10.2 fails to compile the gradient of `geometry.forward_kinematics`
with several batch axes or under `vmap` (hlo verifier / RET_CHECK error on its scatters).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from nmjax import geometry
from nmjax.config import DynamicsConfig

STD_EPS = 1e-4  # std = softplus(raw) + 1e-4 (Fig. 11)
LEAKY_SLOPE = 0.01  # the release's MLPs use LeakyReLU with PyTorch's default negative slope
MODELS = ("nm", "vrnn")


class Buffer(nnx.Variable):
    """A non-trainable array that belongs to the model state (saved, never optimised)."""


class StepOutput(NamedTuple):
    """Per-step outputs of the cell; a scan stacks them along a time axis after the batch axes."""

    keypoints: jax.Array  # (B,K,4) decoded x_hat_t
    rotations: jax.Array  # (B,K,3,3) local rotations (identity for the vrnn baseline)
    z: jax.Array  # (B,D_z) the latent that was decoded
    mean_q: jax.Array  # (B,D_z) posterior mean (equal to the prior when no x_t is seen)
    std_q: jax.Array  # (B,D_z)
    mean_p: jax.Array  # (B,D_z) prior mean
    std_p: jax.Array  # (B,D_z)


def bone_lengths(keypoints: jax.Array, parents: tuple[int, ...] | np.ndarray) -> jax.Array:
    """Bone length of every joint measured on an observed sequence (Eq. 20, released form).

    The paper prints the length in the first frame; the released code takes torch's median over
    time of the keypoint-parent distance (for an even T the lower of the two middle values,
    `lower_median`), which is what this computes.

    Args:
      keypoints: (..., T, K, 4) or (..., T, K, 3) observed keypoints; only xyz is used.
      parents: (K,) parent index of each joint; the root is its own parent (length 0).

    Returns:
      (..., K) lengths ||mu_k - mu_parent(k)||, lower median over T.
    """
    mu = keypoints[..., :3]
    parent_mu = jnp.take(mu, jnp.asarray(parents), axis=-2)
    dist = jnp.linalg.norm(mu - parent_mu, axis=-1)  # (..., T, K)
    return lower_median(dist, axis=-2)


def lower_median(x: jax.Array, axis: int = -1) -> jax.Array:
    """torch.median's median: for an even count the lower of the two middle values (not their
    mean, as `jnp.median`), so the result is always one of the values.

    Args:
      x: (..., N, ...) values.
      axis: the axis reduced.

    Returns:
      x with `axis` removed: the ((N - 1) // 2)-th smallest value along it.
    """
    middle = (x.shape[axis] - 1) // 2
    return jnp.take(jnp.sort(x, axis=axis), middle, axis=axis)


def gaussian_head(raw: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Splits (..., 2 D) into a mean and a std = softplus + 1e-4 (Fig. 11)."""
    mean, raw_std = jnp.split(raw, 2, axis=-1)
    return mean, jax.nn.softplus(raw_std) + STD_EPS


def torch_uniform(fan_in: int) -> nnx.Initializer:
    """PyTorch's default initialisation of nn.Linear and nn.GRUCell: uniform in +-1/sqrt(fan_in).

    nn.Linear draws its weight with kaiming_uniform(a=sqrt(5)), whose bound
    sqrt(1/3) sqrt(3 / fan_in) is 1/sqrt(fan_in), and its bias with the same bound; nn.GRUCell
    draws every weight and bias with bound 1/sqrt(hidden). The release's phase 2 keeps these.
    """
    bound = 1.0 / np.sqrt(fan_in)

    def init(key: jax.Array, shape: tuple[int, ...], dtype=jnp.float32) -> jax.Array:
        return jax.random.uniform(key, shape, dtype, -bound, bound)

    return init


def linear(in_features: int, out_features: int, *, rngs: nnx.Rngs) -> nnx.Linear:
    """nnx.Linear initialised as PyTorch's nn.Linear (`torch_uniform` of its fan-in)."""
    init = torch_uniform(in_features)
    return nnx.Linear(in_features, out_features, kernel_init=init, bias_init=init, rngs=rngs)


class MLP(nnx.Module):
    """Linear -> LeakyReLU(0.01) -> Linear, the shape of every head of Fig. 11 (as released)."""

    def __init__(self, in_features: int, hidden: int, out_features: int, *, rngs: nnx.Rngs):
        self.hidden = linear(in_features, hidden, rngs=rngs)
        self.out = linear(hidden, out_features, rngs=rngs)

    def __call__(self, x: jax.Array) -> jax.Array:
        return self.out(jax.nn.leaky_relu(self.hidden(x), LEAKY_SLOPE))


class GRUCell(nnx.Module):
    """PyTorch's GRU cell (nn.GRUCell), the recurrence of the release's dynamics module.

        r = sigmoid(W_ir x + W_hr h + b_r)
        z = sigmoid(W_iz x + W_hz h + b_z)
        n = tanh(W_in x + b_in + r * (W_hn h + b_hn))
        h' = (1 - z) n + z h

    flax's GRUCell has no b_hn (its hidden-to-hidden dense carries no bias), which changes n
    wherever r < 1. The gates' biases are PyTorch's too: b_ir and b_hr (b_iz and b_hz) are two
    parameters that only enter as a sum, kept apart because under Adam two parameters move their
    sum about twice as fast as one would.

    Attributes:
      input_kernel: (in, 3H) [W_ir, W_iz, W_in] transposed; input_bias: (3H,) [b_ir, b_iz, b_in]
        (PyTorch's bias_ih).
      hidden_kernel: (H, 3H) [W_hr, W_hz, W_hn] transposed; hidden_bias: (3H,) [b_hr, b_hz,
        b_hn] (PyTorch's bias_hh).
    """

    def __init__(self, in_features: int, hidden: int, *, rngs: nnx.Rngs):
        init = torch_uniform(hidden)  # nn.GRUCell bounds every tensor by 1/sqrt(hidden)
        self.hidden = hidden
        self.input_kernel = nnx.Param(init(rngs.params(), (in_features, 3 * hidden)))
        self.hidden_kernel = nnx.Param(init(rngs.params(), (hidden, 3 * hidden)))
        self.input_bias = nnx.Param(init(rngs.params(), (3 * hidden,)))
        self.hidden_bias = nnx.Param(init(rngs.params(), (3 * hidden,)))

    def __call__(self, h: jax.Array, x: jax.Array) -> jax.Array:
        """One step: h (..., H), x (..., in) -> h' (..., H)."""
        xi_r, xi_z, xi_n = jnp.split(x @ self.input_kernel[...] + self.input_bias[...], 3, -1)
        hh = h @ self.hidden_kernel[...] + self.hidden_bias[...]
        hh_r, hh_z, hh_n = jnp.split(hh, 3, axis=-1)
        r = jax.nn.sigmoid(xi_r + hh_r)
        z = jax.nn.sigmoid(xi_z + hh_z)
        n = jnp.tanh(xi_n + r * hh_n)
        return (1.0 - z) * n + z * h


class Dynamics(nnx.Module):
    """The VRNN cell with the Neural Marionette ("nm") or positional ("vrnn") decoder.

    Args:
      cfg: sizes (D_z, D_h, mlp width), decoder kind and S.
      parents: (K,) parent of every keypoint of the extracted skeleton; root is its own parent.
      order: (K,) topological order, root first (skeleton.json "order").
      rngs: parameter and offset-direction initialisation; `rngs.params()` draws the offset
        directions, so a seed fixes them.
    """

    def __init__(
        self,
        cfg: DynamicsConfig,
        parents: tuple[int, ...] | list[int] | np.ndarray,
        order: tuple[int, ...] | list[int] | np.ndarray,
        *,
        rngs: nnx.Rngs,
    ):
        if cfg.model not in MODELS:
            raise ValueError(f"DynamicsConfig.model={cfg.model!r}; valid models: {MODELS}")
        parents = tuple(int(p) for p in parents)
        order = tuple(int(k) for k in order)
        num_keypoints = len(parents)
        if sorted(order) != list(range(num_keypoints)) or parents[order[0]] != order[0]:
            raise ValueError(
                f"skeleton order {order} must be a permutation of 0..{num_keypoints - 1} "
                "starting at the root (the joint that is its own parent)"
            )
        self.kind = cfg.model
        self.parents = parents
        self.order = order
        self.num_keypoints = num_keypoints
        self.latent = cfg.latent
        self.samples = cfg.posterior_samples
        k, dz, dh, m = num_keypoints, cfg.latent, cfg.hidden, cfg.mlp
        x_dim = 4 * k

        self.posterior = MLP(dh + x_dim, m, 2 * dz, rngs=rngs)
        self.prior = MLP(dh, m, 2 * dz, rngs=rngs)
        if self.kind == "nm":
            self.global_decoder = MLP(dh + dz, m, 3 + k, rngs=rngs)
            self.rotation_decoder = MLP(dh + dz, m, 6 * k, rngs=rngs)
            directions = jax.random.normal(rngs.params(), (k, 3))
            directions = directions / jnp.linalg.norm(directions, axis=-1, keepdims=True)
            self.directions = Buffer(directions)  # \bar d_k of Eq. 20, fixed at initialisation
        else:
            self.keypoint_decoder = MLP(dh + dz, m, x_dim, rngs=rngs)
        self.rnn = GRUCell(x_dim + dz, dh, rngs=rngs)
        # The release's init_kypt_rnn_state: a learned state drawn N(0, 1), not zeros.
        self.initial_hidden = nnx.Param(jax.random.normal(rngs.params(), (dh,)))

    # -- pieces of one step ------------------------------------------------------------------

    def offsets(self, lengths: jax.Array) -> jax.Array:
        """Offsets d_k = \\bar d_k ||bone_k|| (Eq. 20): (..., K) lengths -> (..., K, 3)."""
        return self.directions[...] * lengths[..., None]

    def decode(self, h: jax.Array, z: jax.Array, lengths: jax.Array) -> tuple[jax.Array, jax.Array]:
        """x_hat = phi(z, h) (Eqs. 3, 18, 19 and 2).

        Args:
          h: (..., D_h) hidden state.
          z: (..., D_z) latent.
          lengths: (..., K) bone lengths of the observed sequence (unused by "vrnn").

        Returns:
          keypoints (..., K, 4) and local rotations (..., K, 3, 3) (identity for "vrnn").
        """
        hz = jnp.concatenate([h, z], axis=-1)
        k = self.num_keypoints
        batch = hz.shape[:-1]
        if self.kind == "vrnn":
            keypoints = self.keypoint_decoder(hz).reshape(*batch, k, 4)
            rotations = jnp.broadcast_to(jnp.eye(3), (*batch, k, 3, 3))
            return keypoints, rotations
        y = jnp.tanh(self.global_decoder(hz))  # (..., 3 + K)
        root, alpha = y[..., :3], (y[..., 3:] + 1.0) / 2.0
        # As released, the 6D vector is the decoder's output itself: an untrained decoder
        # outputs its random bias, i.e. random rotations.
        rot6d = self.rotation_decoder(hz).reshape(*batch, k, 6)
        rotations = geometry.rotation_6d_to_matrix(rot6d)
        offsets = jnp.broadcast_to(self.offsets(lengths), (*batch, k, 3))
        # FK on one flattened batch axis: with several leading axes, XLA:CPU (jax 0.10.2) fails
        # to compile the gradient of geometry.forward_kinematics's scatters (hlo verifier error).
        mu = geometry.forward_kinematics(
            root.reshape(-1, 3),
            rotations.reshape(-1, k, 3, 3),
            offsets.reshape(-1, k, 3),
            self.parents,
            self.order,
        ).reshape(*batch, k, 3)
        return jnp.concatenate([mu, alpha[..., None]], axis=-1), rotations

    def prior_dist(self, h: jax.Array) -> tuple[jax.Array, jax.Array]:
        """p(z_t | h_t): (..., D_h) -> mean, std (..., D_z)."""
        return gaussian_head(self.prior(h))

    def posterior_dist(self, h: jax.Array, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        """q(z_t | h_t, x_t): h (..., D_h), x (..., K, 4) -> mean, std (..., D_z)."""
        x_flat = x.reshape(*x.shape[:-2], -1)
        return gaussian_head(self.posterior(jnp.concatenate([h, x_flat], axis=-1)))

    def recur(self, h: jax.Array, x_hat: jax.Array, z: jax.Array) -> jax.Array:
        """h_{t+1} = GRU(h_t, [x_hat_t, z_t])."""
        x_flat = x_hat.reshape(*x_hat.shape[:-2], -1)
        return self.rnn(h, jnp.concatenate([x_flat, z], axis=-1))

    def posterior_step(
        self, h: jax.Array, x: jax.Array, lengths: jax.Array, key: jax.Array, samples: int
    ) -> tuple[jax.Array, StepOutput]:
        """One observed step with best-of-S posterior sampling.

        Draws `samples` latents from q(z_t | h_t, x_t), decodes them together and keeps, per
        batch element, the one whose decoding has the smallest squared error to x_t.

        Args:
          h: (B, D_h); x: (B, K, 4); lengths: (B, K); key: PRNG key of this step.
          samples: S (static).

        Returns:
          h_{t+1} (B, D_h) and the StepOutput of the kept sample.
        """
        mean_p, std_p = self.prior_dist(h)
        mean_q, std_q = self.posterior_dist(h, x)
        eps = jax.random.normal(key, (samples, *mean_q.shape))
        z_all = mean_q + std_q * eps  # (S, B, D_z)
        # The choice is not differentiable and only the kept sample carries gradient, so the S
        # candidates are decoded without it and the kept one is decoded again with it: the same
        # gradient as differentiating through all S decodings, at the backward cost of one.
        x_all, _ = jax.lax.stop_gradient(
            self.decode(
                jnp.broadcast_to(h, (samples, *h.shape)),
                z_all,
                jnp.broadcast_to(lengths, (samples, *lengths.shape)),
            )
        )  # the S samples ride along as a leading batch axis
        error = jnp.sum((x_all - x) ** 2, axis=(-2, -1))  # (S, B)
        best = jnp.argmin(error, axis=0)  # (B,)
        z = jax.vmap(lambda a, i: a[i], in_axes=(1, 0))(z_all, best)  # (S, B, D_z) -> (B, D_z)
        x_hat, rotations = self.decode(h, z, lengths)
        out = StepOutput(x_hat, rotations, z, mean_q, std_q, mean_p, std_p)
        return self.recur(h, x_hat, z), out

    def prior_step(
        self, h: jax.Array, lengths: jax.Array, key: jax.Array
    ) -> tuple[jax.Array, StepOutput]:
        """One unobserved step: z_t ~ p(z_t | h_t), decode, recur. Shapes as `posterior_step`."""
        mean_p, std_p = self.prior_dist(h)
        z = mean_p + std_p * jax.random.normal(key, mean_p.shape)
        x_hat, rotations = self.decode(h, z, lengths)
        out = StepOutput(x_hat, rotations, z, mean_p, std_p, mean_p, std_p)
        return self.recur(h, x_hat, z), out

    def initial_state(self, batch: int) -> jax.Array:
        """The learned initial hidden state broadcast to (B, D_h)."""
        return jnp.broadcast_to(self.initial_hidden[...], (batch, self.initial_hidden.shape[-1]))

    # -- whole sequences ---------------------------------------------------------------------

    def __call__(
        self,
        x: jax.Array,
        key: jax.Array,
        samples: int | None = None,
        lengths: jax.Array | None = None,
    ) -> StepOutput:
        """Runs the posterior over an observed sequence (training / reconstruction).

        Args:
          x: (B, T, K, 4) keypoint trajectories.
          key: PRNG key; split into T per-step keys up front.
          samples: S of the best-of-S rule; default the config's `posterior_samples`.
          lengths: (B, K) bone lengths; default measured on `x` (Eq. 20).

        Returns:
          StepOutput whose fields have a time axis: keypoints (B,T,K,4), rotations (B,T,K,3,3),
          z / means / stds (B,T,D_z).
        """
        samples = self.samples if samples is None else samples
        if lengths is None:
            lengths = bone_lengths(x, self.parents)
        keys = jax.random.split(key, x.shape[1])

        def step(h, inputs):
            x_t, key_t = inputs
            return self.posterior_step(h, x_t, lengths, key_t, samples)

        _, outs = jax.lax.scan(step, self.initial_state(x.shape[0]), (jnp.swapaxes(x, 0, 1), keys))
        return jax.tree.map(lambda a: jnp.swapaxes(a, 0, 1), outs)

    def reconstruct(
        self, x: jax.Array, key: jax.Array, samples: int = 1
    ) -> tuple[jax.Array, jax.Array]:
        """Posterior reconstruction: (B,T,K,4) -> keypoints (B,T,K,4), rotations (B,T,K,3,3)."""
        out = self(x, key, samples=samples)
        return out.keypoints, out.rotations

    def generate(
        self, x_cond: jax.Array, num_frames: int, key: jax.Array, samples: int | None = None
    ) -> tuple[jax.Array, jax.Array]:
        """Motion generation (Sec. 5): T_cond posterior steps, then `num_frames` prior samples.

        The observed frames are inferred with the training rule, best of S posterior samples per
        step (the release's generation uses its S = 10). Bone lengths are measured on the
        conditioning frames (Eq. 20), so every generated frame of the "nm" model keeps them
        exactly.

        Args:
          x_cond: (B, T_cond, K, 4) observed keypoints.
          num_frames: T_gen (static).
          key: PRNG key.
          samples: S of the best-of-S rule on the observed frames (static); default the config's
            `posterior_samples`, 1 = one posterior sample per step.

        Returns:
          keypoints (B, T_cond + T_gen, K, 4) and local rotations (B, T_cond + T_gen, K, 3, 3).
        """
        samples = self.samples if samples is None else samples
        lengths = bone_lengths(x_cond, self.parents)
        key_cond, key_gen = jax.random.split(key)
        keys_cond = jax.random.split(key_cond, x_cond.shape[1])
        keys_gen = jax.random.split(key_gen, num_frames)

        def observed(h, inputs):
            x_t, key_t = inputs
            return self.posterior_step(h, x_t, lengths, key_t, samples)

        def unobserved(h, key_t):
            return self.prior_step(h, lengths, key_t)

        h0 = self.initial_state(x_cond.shape[0])
        h, cond = jax.lax.scan(observed, h0, (jnp.swapaxes(x_cond, 0, 1), keys_cond))
        _, gen = jax.lax.scan(unobserved, h, keys_gen)
        keypoints = jnp.concatenate([cond.keypoints, gen.keypoints], axis=0)
        rotations = jnp.concatenate([cond.rotations, gen.rotations], axis=0)
        return jnp.swapaxes(keypoints, 0, 1), jnp.swapaxes(rotations, 0, 1)
