"""The articulated refinement after phase 1 (docs/architecture.md §7b), pure JAX and optax.

Phase 1 leaves a tree (Algorithm 1) and per-frame keypoints: soft-argmax averages over the
heatmap cells, whose bones change length from frame to frame and whose rotations, read off the
bones, carry no twist. The refinement fits one articulated model to one sequence's points:

- parameters: the rest root position and one rest offset d_k per joint from its parent (so every
  bone keeps its length ||d_k|| in every frame by construction), per-frame local rotations in
  the 6D representation (as phase 2's decoder, Eq. 19, `geometry.rotation_6d_to_matrix`), the
  per-frame root position, and optionally the skin weights as softmax logits;
- the motion: forward kinematics along the tree (Eq. 2, mu_k = mu_parent + R_k d_k with
  R_k = R_parent R~_k, `geometry.forward_kinematics_with_rotations`); the rest pose is the same
  offsets with identity rotations;
- the surface: the rest surface (a sequence's frame-0 points) skinned by linear blend skinning
  (`geometry.linear_blend_skinning`), joint k moving v to R_k (v - r_k) + mu_k (r_k its rest
  position), which moves the bone from k's parent to k rigidly;
- the objective, per frame and averaged over frames (one jitted loss, `vmap` over frames): the
  symmetric Chamfer distance of squared distances (`metrics.chamfer_distance`, Table 2's
  definition) between the skinned surface and `target_points` of the frame's points drawn anew
  every iteration (fixed seed), plus three small priors:

      L = mean_t CD(LBS_t(surface), points_t)
          + smooth_weight  * mean_{t,k} ||R~_{t+1,k} - 2 R~_{t,k} + R~_{t-1,k}||_F^2
          + entropy_weight * mean_v (-sum_k w_vk log w_vk)
          + offset_weight  * mean_k ||d_k - d_k^0||^2,

  the squared second differences of the local rotation matrices over time (temporal
  smoothness; a constant angular velocity of w radians a frame costs only about 2 w^4), the
  skin weights' entropy (a vertex leans to one joint, as a rigid link's points do) and the rest
  offsets' squared distance to their start d^0 (phase 1's bones). The last holds what the
  surface does not see: a leaf's offset moves no vertex, nor does a joint's position along its
  hinge axis, and without it Adam lets such offsets wander with the noise of the drawn points
  (a finger's bone grew to the whole cube in 300 steps);
- the start: phase 1's keypoints of the kept nodes with the rotations `nmjax export` gives them
  (swing only, rest pose frame 0, `nmjax.export.rig.swing_rotations`), each bone's length the
  median over the frames of its keypoint length, and Algorithm 2's skin weights
  (`initial_params`);
- the optimiser: Adam (optax) with a cosine decay to `final_lr_fraction` of the rate over a fixed
  number of iterations, one compiled step (`fit`), deterministic for a seed.

"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax import Array

from nmjax import geometry
from nmjax.metrics.chamfer import chamfer_distance

# The smallest weight Algorithm 2's weights are raised to before their logarithm becomes a
# logit: a joint the vertex does not use starts at ~1e-3 of its weight, near nothing, yet with a
# gradient that can grow it.
WEIGHT_FLOOR = 1e-3
PARAM_KEYS = ("rest_root", "offsets", "rotations", "root", "logits")


@dataclasses.dataclass(frozen=True)
class RefineSettings:
    """The refinement's settings (module docstring); every field is part of what it computes.

    Attributes:
      iterations: Adam steps (a fixed budget).
      learning_rate: Adam's rate for the joints (rest offsets, rotations, root), decayed by a
        cosine to `final_lr_fraction` of it.
      weight_learning_rate: the same for the skin weights' logits (a logit moves by about this
        much per step; a weight from 0.5 to 0.9 is a change of 2.2).
      final_lr_fraction: the rate at the last step, as a fraction of the first.
      surface_points: rest-surface points skinned (a fixed subset of frame 0's).
      target_points: points of every frame the Chamfer compares against, drawn anew each
        iteration (all of them when a frame has no more).
      smooth_weight: weight of the rotations' temporal smoothness.
      entropy_weight: weight of the skin weights' entropy.
      offset_weight: weight of the rest offsets' squared distance to their start.
      fit_weights: fit the skin weights too; False keeps Algorithm 2's.
      seed: the draws of the surface subset and of every iteration's target points.
    """

    iterations: int = 300
    learning_rate: float = 1e-2
    weight_learning_rate: float = 5e-2
    final_lr_fraction: float = 0.1
    surface_points: int = 512
    target_points: int = 512
    smooth_weight: float = 1e-3
    entropy_weight: float = 1e-4
    offset_weight: float = 1e-2
    fit_weights: bool = True
    seed: int = 0

    def __post_init__(self):
        for name in ("iterations", "surface_points", "target_points"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"refine: {name} must be >= 1, got {getattr(self, name)}")
        for name in ("learning_rate", "weight_learning_rate", "final_lr_fraction"):
            if not float(getattr(self, name)) > 0:
                raise ValueError(f"refine: {name} must be > 0, got {getattr(self, name)}")
        for name in ("smooth_weight", "entropy_weight", "offset_weight"):
            if not float(getattr(self, name)) >= 0:
                raise ValueError(f"refine: {name} must be >= 0, got {getattr(self, name)}")


def tree_order(parents: Sequence[int] | np.ndarray) -> tuple[int, ...]:
    """A topological order of the tree `parents` (root its own parent), root first, breadth
    first with children in index order (static: for forward kinematics)."""
    parents = np.asarray(parents, np.int64).reshape(-1)
    roots = np.flatnonzero(parents == np.arange(len(parents)))
    if roots.size != 1:
        raise ValueError(f"refine: parents {parents.tolist()} must have exactly one root")
    order, frontier = [], [int(roots[0])]
    while frontier:
        order += frontier
        frontier = [c for p in frontier for c in np.flatnonzero(parents == p).tolist() if c != p]
    if len(order) != len(parents):
        raise ValueError(f"refine: parents {parents.tolist()} are not a tree (a cycle)")
    return tuple(order)


# --- parameters --------------------------------------------------------------------------------


def initial_params(
    positions: Any,
    rotations: Any,
    rest_positions: Any,
    parents: Sequence[int] | np.ndarray,
    weights: Any,
) -> dict[str, Array]:
    """The start of the refinement from an unrefined rig (positions, world rotations, rest pose
    with identity rotations, `nmjax.export.rig.Rig`'s convention) and its skin weights.

    Each rest offset points along the rig's rest bone (mu_k - mu_parent at rest) with the median
    over the frames of the rig's bone length; the local rotations are R_parent^T R_k of the
    rig's world rotations (the root's its world rotation); the root follows the rig's root.

    Args:
      positions: (T, J, 3) joint positions; rotations: (T, J, 3, 3) world rotations relative to
        the rest pose; rest_positions: (J, 3); parents: (J,) the tree, root its own parent.
      weights: (V, J) skin weights of the rest surface, rows summing to 1.

    Returns:
      {"rest_root" (3,), "offsets" (J, 3), "rotations" (T, J, 6), "root" (T, 3),
       "logits" (V, J)}, float32.
    """
    parents = np.asarray(parents, np.int64).reshape(-1)
    positions = np.asarray(positions, np.float64)
    rotations = np.asarray(rotations, np.float64)
    rest = np.asarray(rest_positions, np.float64)
    weights = np.asarray(weights, np.float64)
    num = len(parents)
    if positions.ndim != 3 or positions.shape[1:] != (num, 3):
        raise ValueError(f"refine: positions must be (T, {num}, 3), got {positions.shape}")
    if rotations.shape != (*positions.shape, 3):
        raise ValueError(
            f"refine: rotations must be {(*positions.shape, 3)}, got {rotations.shape}"
        )
    if rest.shape != (num, 3) or weights.ndim != 2 or weights.shape[1] != num:
        raise ValueError(
            f"refine: rest positions ({num}, 3) and weights (V, {num}) expected, got "
            f"{rest.shape} and {weights.shape}"
        )
    root = tree_order(parents)[0]
    lengths = np.median(np.linalg.norm(positions - positions[:, parents], axis=-1), axis=0)
    rest_bone = rest - rest[parents]
    norm = np.linalg.norm(rest_bone, axis=-1, keepdims=True)
    offsets = np.where(norm > 1e-12, rest_bone / np.maximum(norm, 1e-12), 0.0) * lengths[:, None]
    local = np.swapaxes(rotations[:, parents], -1, -2) @ rotations
    local[:, root] = rotations[:, root]
    six = np.concatenate([local[..., :, 0], local[..., :, 1]], axis=-1)  # matrix_to_rotation_6d
    return {
        "rest_root": jnp.asarray(rest[root], jnp.float32),
        "offsets": jnp.asarray(offsets, jnp.float32),
        "rotations": jnp.asarray(six, jnp.float32),
        "root": jnp.asarray(positions[:, root], jnp.float32),
        "logits": jnp.asarray(np.log(np.maximum(weights, 0.0) + WEIGHT_FLOOR), jnp.float32),
    }


def rest_joints(params: dict[str, Array], parents, order) -> Array:
    """(J, 3) the rest pose: the offsets placed by forward kinematics with identity rotations."""
    num = params["offsets"].shape[0]
    eye = jnp.broadcast_to(jnp.eye(3, dtype=params["offsets"].dtype), (num, 3, 3))
    return geometry.forward_kinematics(params["rest_root"], eye, params["offsets"], parents, order)


def articulate(params: dict[str, Array], parents, order) -> tuple[Array, Array, Array]:
    """The model's motion: (positions (..., T, J, 3), world rotations (..., T, J, 3, 3), local
    rotations (..., T, J, 3, 3)) by Eq. 2 from the parameters (`parents`, `order` static)."""
    local = geometry.rotation_6d_to_matrix(params["rotations"])
    positions, world = geometry.forward_kinematics_with_rotations(
        params["root"], local, params["offsets"], parents, order
    )
    return positions, world, local


def skin_weights(params: dict[str, Array]) -> Array:
    """(V, J) the skin weights: softmax of the logits over the joints."""
    return jax.nn.softmax(params["logits"], axis=-1)


@jax.jit
def skin(positions: Array, world: Array, rest: Array, weights: Array, surface: Array) -> Array:
    """The rest surface posed by linear blend skinning (appendix A.4): joint k moves v to
    R_k (v - r_k) + mu_k, blended by the weights.

    Args:
      positions: (..., J, 3), world: (..., J, 3, 3) the pose; rest: (J, 3) the rest joints r_k
        (rest rotations identity); weights: (V, J); surface: (V, 3) in the rest pose.

    Returns:
      (..., V, 3).
    """
    translations = positions - jnp.einsum("...kij,kj->...ki", world, rest)
    return geometry.linear_blend_skinning(
        surface, weights, rotations=world, translations=translations
    )


# --- the objective -----------------------------------------------------------------------------


def _frame_chamfer(six, root, offsets, rest, weights, surface, target, parents, order):
    """One frame's Chamfer distance: (J, 6), (3,) of the frame, target (M, 3) -> scalar."""
    local = geometry.rotation_6d_to_matrix(six)
    positions, world = geometry.forward_kinematics_with_rotations(
        root, local, offsets, parents, order
    )
    return chamfer_distance(skin(positions, world, rest, weights, surface), target)


def rotation_smoothness(local: Array) -> Array:
    """mean_{t,k} ||R~_{t+1,k} - 2 R~_{t,k} + R~_{t-1,k}||_F^2 of (T, J, 3, 3) local rotations
    (0 with fewer than 3 frames)."""
    if local.shape[0] < 3:
        return jnp.zeros((), local.dtype)
    second = local[2:] - 2.0 * local[1:-1] + local[:-2]
    return jnp.mean(jnp.sum(jnp.square(second), axis=(-1, -2)))


def weight_entropy(logits: Array) -> Array:
    """mean_v -sum_k w_vk log w_vk of the skin weights w = softmax(logits), (V, J) -> scalar."""
    log_w = jax.nn.log_softmax(logits, axis=-1)
    return jnp.mean(-jnp.sum(jnp.exp(log_w) * log_w, axis=-1))


def objective(
    params: dict[str, Array],
    surface: Array,
    targets: Array,
    anchor: Array,
    parents,
    order,
    settings: RefineSettings,
) -> tuple[Array, dict[str, Array]]:
    """The refinement's objective L of the module docstring.

    Args:
      params: `initial_params`'s dict; surface: (V, 3) rest surface; targets: (T, M, 3) every
        frame's points; anchor: (J, 3) the rest offsets the fit started from; parents, order:
        the tree (static); settings: the priors' weights and whether the weights are fitted
        (else they enter without gradient).

    Returns:
      (L, {"chamfer", "smooth", "entropy", "offset"}: the unweighted terms).
    """
    logits = params["logits"] if settings.fit_weights else jax.lax.stop_gradient(params["logits"])
    weights = jax.nn.softmax(logits, axis=-1)
    rest = rest_joints(params, parents, order)
    frame = functools.partial(_frame_chamfer, parents=parents, order=order)
    chamfers = jax.vmap(frame, in_axes=(0, 0, None, None, None, None, 0))(
        params["rotations"], params["root"], params["offsets"], rest, weights, surface, targets
    )
    terms = {
        "chamfer": jnp.mean(chamfers),
        "smooth": rotation_smoothness(geometry.rotation_6d_to_matrix(params["rotations"])),
        "entropy": weight_entropy(logits),
        "offset": jnp.mean(jnp.sum(jnp.square(params["offsets"] - anchor), axis=-1)),
    }
    total = (
        terms["chamfer"]
        + settings.smooth_weight * terms["smooth"]
        + settings.entropy_weight * terms["entropy"]
        + settings.offset_weight * terms["offset"]
    )
    return total, terms


# --- the fit -----------------------------------------------------------------------------------


def optimizer(settings: RefineSettings) -> optax.GradientTransformation:
    """Adam with a cosine decay over the iterations, its own rate for the skin weights."""

    def adam(rate: float) -> optax.GradientTransformation:
        schedule = optax.cosine_decay_schedule(
            rate, settings.iterations, alpha=settings.final_lr_fraction
        )
        return optax.adam(schedule)

    labels = {key: "weights" if key == "logits" else "joints" for key in PARAM_KEYS}
    return optax.multi_transform(
        {"joints": adam(settings.learning_rate), "weights": adam(settings.weight_learning_rate)},
        labels,
    )


def frame_targets(frames: Array, key: Array, count: int) -> Array:
    """(T, count, 3): `count` points of every frame (T, N, 3) drawn with replacement by `key`;
    the frames themselves when count >= N."""
    if count >= frames.shape[1]:
        return frames
    index = jax.random.randint(key, (frames.shape[0], count), 0, frames.shape[1])
    return jnp.take_along_axis(frames, index[..., None], axis=1)


@functools.partial(
    jax.jit, static_argnames=("parents", "order", "settings"), donate_argnames=("params", "state")
)
def _step(params, state, step, surface, frames, anchor, key, parents, order, settings):
    targets = frame_targets(frames, jax.random.fold_in(key, step), settings.target_points)
    (_, terms), grads = jax.value_and_grad(objective, has_aux=True)(
        params, surface, targets, anchor, parents, order, settings
    )
    updates, state = optimizer(settings).update(grads, state, params)
    return optax.apply_updates(params, updates), state, terms


def fit(
    params: dict[str, Array],
    surface: Any,
    frames: Any,
    parents: Sequence[int] | np.ndarray,
    settings: RefineSettings = RefineSettings(),
    *,
    progress: bool = True,
    desc: str = "refine",
) -> tuple[dict[str, Array], dict[str, np.ndarray]]:
    """Minimises `objective` from `params` for `settings.iterations` Adam steps.

    Args:
      params: the start (`initial_params`).
      surface: (V, 3) rest surface; frames: (T, N, 3) every frame's points (same cube).
      parents: (J,) the tree.
      settings: the refinement's settings.
      progress: a tqdm bar over the iterations.
      desc: the bar's label.

    Returns:
      (the fitted parameters, {"chamfer", "smooth", "entropy", "offset"}: (iterations,) each
      term at every step, before that step's update).
    """
    from tqdm import tqdm

    parents = tuple(int(p) for p in np.asarray(parents).reshape(-1))
    order = tree_order(parents)
    surface = jnp.asarray(surface, jnp.float32)
    frames = jnp.asarray(frames, jnp.float32)
    if frames.ndim != 3 or frames.shape[0] != params["root"].shape[0] or frames.shape[2] != 3:
        raise ValueError(
            f"refine: frames must be (T, N, 3) with T={params['root'].shape[0]}, the motion's "
            f"frames; got {frames.shape}"
        )
    if surface.ndim != 2 or surface.shape != (params["logits"].shape[0], 3):
        raise ValueError(
            f"refine: surface must be ({params['logits'].shape[0]}, 3), one point per weight "
            f"row; got {surface.shape}"
        )
    params = {k: jnp.array(params[k], jnp.float32) for k in PARAM_KEYS}  # a copy: donated
    anchor = jnp.array(params["offsets"])
    state = optimizer(settings).init(params)
    key = jax.random.key(settings.seed)
    history: dict[str, list] = {"chamfer": [], "smooth": [], "entropy": [], "offset": []}
    bar = tqdm(range(settings.iterations), desc=desc, unit="it", disable=not progress)
    for step in bar:  # optimisation steps: each one compiled call
        params, state, terms = _step(
            params, state, step, surface, frames, anchor, key, parents, order, settings
        )
        for name, value in terms.items():
            history[name].append(value)
        if progress and (step % 25 == 0 or step == settings.iterations - 1):
            bar.set_postfix(chamfer_x1e4=f"{float(terms['chamfer']) * 1e4:.1f}")
    return params, {k: np.asarray(jax.device_get(v), np.float64) for k, v in history.items()}


@functools.partial(jax.jit, static_argnames=("parents", "order"))
def _refined(params, parents, order):
    positions, world, local = articulate(params, parents, order)
    return {
        "rest_positions": rest_joints(params, parents, order),
        "offsets": params["offsets"],
        "local_rotations": local,
        "rotations": world,
        "positions": positions,
        "root": params["root"],
        "weights": skin_weights(params),
    }


def refined_arrays(params: dict[str, Array], parents) -> dict[str, np.ndarray]:
    """The refined skeleton as NumPy arrays.

    Returns:
      {"rest_positions" (J, 3), "offsets" (J, 3), "local_rotations" (T, J, 3, 3),
       "rotations" (T, J, 3, 3) world, "positions" (T, J, 3), "root" (T, 3),
       "weights" (V, J)}, float32.
    """
    parents = tuple(int(p) for p in np.asarray(parents).reshape(-1))
    out = _refined(params, parents, tree_order(parents))
    return {k: np.asarray(v, np.float32) for k, v in out.items()}
