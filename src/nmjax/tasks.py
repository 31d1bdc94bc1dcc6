"""What the learned model is for (paper Sec. 5, appendix A.4 and D.4; DESIGN section 9).

- Motion generation: the T_cond observed frames (run through the posterior), then prior samples
  to T_cond + T_gen frames, several samples per input (`generate_motion`).
- Motion interpolation between keyframes x_ts and x_te: the posterior at x_ts, then the prior
  rolled over the gap for several trajectories, keeping the one that ends closest to x_te
  (`interpolate_motion`), next to the non-generative baselines Lerp (joint positions,
  `lerp_keypoints`) and Slerp (local rotations inferred by the model, `slerp_keypoints`). The
  positional VRNN baseline is `interpolate_motion` with a `Dynamics` of kind "vrnn".
- Motion retargeting (Eqs. 24-25): source local rotations with target bone offsets
  (`retarget_joints`), skin weights (Algorithm 2, `nmjax.skeleton.skin_weights`) and linear blend
  skinning of a target mesh (`retarget_vertices`), together `retarget_mesh`; `load_mesh` validates
  a user's mesh.

The array functions are pure and jit-able; sampling is vmapped over trajectories. What was
observed is returned as given: a generated motion starts with its conditioning frames, and in
every interpolation result the two keyframes are the given ones (the methods differ only in the
frames between them).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from nmjax import atomic, geometry, runs
from nmjax.config import DynTrainConfig
from nmjax.data.datasets import pad_with_last
from nmjax.models.dynamics import Dynamics, bone_lengths

# --- generation -----------------------------------------------------------------------------


def generate_motion(
    model: Dynamics,
    x_cond: jax.Array,
    num_frames: int,
    key: jax.Array,
    num_samples: int,
    posterior_samples: int | None = None,
) -> tuple[jax.Array, jax.Array]:
    """Motion generation (Sec. 5): several futures of each conditioning sequence.

    The model runs T_cond posterior steps on the observed frames (best of `posterior_samples`
    latents per step, as in training and in the release's generation), then T_gen prior steps.
    The motion returned starts with the observed frames themselves, not their posterior
    reconstructions: a generated motion continues what was observed.

    Args:
      model: trained dynamics module ("nm" or "vrnn").
      x_cond: (B, T_cond, K, 4) observed keypoints.
      num_frames: T_gen, frames sampled from the prior after the observed ones (static).
      key: PRNG key; one sub-key per sample.
      num_samples: S, independent futures per input (static), drawn under `vmap`.
      posterior_samples: latents drawn per observed frame, the closest kept (static); default
        the model's configured `posterior_samples` (10), 1 = one posterior sample per step.

    Returns:
      keypoints (B, S, T_cond + T_gen, K, 4), the first T_cond frames equal to x_cond in every
      sample, and local rotations (B, S, T_cond + T_gen, K, 3, 3) (identity for "vrnn"), those of
      the first T_cond frames inferred by the posterior.
    """
    keys = jax.random.split(key, num_samples)
    kp, rot = jax.vmap(lambda k: model.generate(x_cond, num_frames, k, posterior_samples))(
        keys
    )  # (S, B, ...)
    kp, rot = jnp.swapaxes(kp, 0, 1), jnp.swapaxes(rot, 0, 1)  # (B, S, ...)
    t_cond = x_cond.shape[1]
    observed = jnp.broadcast_to(x_cond[:, None], (kp.shape[0], num_samples, *x_cond.shape[1:]))
    return jnp.concatenate([observed.astype(kp.dtype), kp[:, :, t_cond:]], axis=2), rot


# --- interpolation --------------------------------------------------------------------------


def interpolate_motion(
    model: Dynamics,
    x_start: jax.Array,
    x_end: jax.Array,
    gap: int,
    key: jax.Array,
    num_trajectories: int,
    posterior_samples: int | None = None,
) -> jax.Array:
    """Generative interpolation (Sec. 5, Motion Interpolation) between two keyframes.

    z is drawn from the posterior at the start keyframe (after any earlier context frames; best
    of `posterior_samples` per observed frame, default the model's S), then the prior is rolled
    for `gap` frames; of `num_trajectories` rollouts (vmapped) the one whose last frame has the
    smallest squared xyz distance to `x_end` is kept.

    Args:
      model: dynamics module ("nm": Neural Marionette; "vrnn": the positional baseline).
      x_start: (B, C, K, 4) observed frames ending with the start keyframe x_ts (C = 1 is the
        paper's setting).
      x_end: (B, K, 4) the end keyframe x_te.
      gap: te - ts, the number of frames generated after x_ts (static, >= 1).
      key: PRNG key.
      num_trajectories: rollouts to choose from (static).
      posterior_samples: S of the best-of-S rule on the observed frames (static); default the
        model's, 1 = one posterior sample per step.

    Returns:
      (B, gap + 1, K, 4): x_ts, the gap - 1 generated in-between frames, then x_te.
    """
    keys = jax.random.split(key, num_trajectories)
    kp, _ = jax.vmap(lambda k: model.generate(x_start, gap, k, posterior_samples))(
        keys
    )  # (N, B, C + gap, K, 4)
    rollout = kp[:, :, x_start.shape[1] :]  # (N, B, gap, K, 4)
    error = jnp.sum(jnp.square(rollout[:, :, -1, :, :3] - x_end[None, :, :, :3]), axis=(-2, -1))
    best = jnp.argmin(error, axis=0)  # (B,)
    chosen = jnp.take_along_axis(rollout, best[None, :, None, None, None], axis=0)[0]
    return jnp.concatenate([x_start[:, -1:], chosen[:, :-1], x_end[:, None]], axis=1)


def interpolation_weights(gap: int) -> jax.Array:
    """(gap + 1,) parameters s = 0, 1/gap, ..., 1 of the frames ts..te."""
    return jnp.arange(gap + 1, dtype=jnp.float32) / gap


def lerp_keypoints(x_start: jax.Array, x_end: jax.Array, gap: int) -> jax.Array:
    """Lerp baseline: joint positions (and intensities) linearly interpolated.

    Args:
      x_start, x_end: (..., K, 4) keyframes.
      gap: te - ts (static, >= 1).

    Returns:
      (..., gap + 1, K, 4), frame i = (1 - i/gap) x_start + (i/gap) x_end.
    """
    s = interpolation_weights(gap)[:, None, None]
    return (1.0 - s) * x_start[..., None, :, :] + s * x_end[..., None, :, :]


def infer_rotations(
    model: Dynamics, x: jax.Array, key: jax.Array, samples: int | None = None
) -> tuple[jax.Array, jax.Array]:
    """Local rotations and root positions the model infers for observed keypoints.

    Best-of-S posterior reconstruction (the training rule), bone lengths measured on `x`.

    Args:
      model: an "nm" dynamics module.
      x: (B, T, K, 4) keypoints.
      key: PRNG key.
      samples: S; default the model's.

    Returns:
      local rotations (B, T, K, 3, 3) and reconstructed keypoints (B, T, K, 4).
    """
    out = model(x, key, samples=samples)
    return out.rotations, out.keypoints


def slerp_keypoints(
    model: Dynamics, x_start: jax.Array, x_end: jax.Array, gap: int, key: jax.Array
) -> jax.Array:
    """Slerp baseline: local rotations inferred by Neural Marionette, spherically interpolated.

    The model infers each keyframe's local rotations on its own (one observed frame from the
    initial state, best-of-S posterior with the same key, bone lengths measured on the two
    keyframes), so equal keyframes get equal rotations; every in-between frame uses
    slerp(R_ts, R_te, s) per joint, the linearly interpolated root position and intensities,
    and forward kinematics (Eq. 2) with the model's offsets (Eq. 20).

    Args:
      model: an "nm" dynamics module.
      x_start, x_end: (B, K, 4) keyframes.
      gap: te - ts (static, >= 1).
      key: PRNG key of the posterior samples.

    Returns:
      (B, gap + 1, K, 4) with the given keyframes at both ends.
    """
    pair = jnp.stack([x_start, x_end], axis=1)  # (B, 2, K, 4)
    lengths = bone_lengths(pair, model.parents)  # (B, K)
    r_start, r_end = (
        model(x[:, None], key, lengths=lengths).rotations[:, 0] for x in pair.swapaxes(0, 1)
    )
    rotations = jnp.stack([r_start, r_end], axis=1)  # (B, 2, K, 3, 3)
    s = interpolation_weights(gap)  # (F,)
    local = geometry.slerp_matrices(
        rotations[:, None, 0], rotations[:, None, 1], s[None, :, None]
    )  # (B, F, K, 3, 3)
    lerped = lerp_keypoints(x_start, x_end, gap)  # (B, F, K, 4)
    root = model.order[0]
    offsets = model.offsets(lengths)  # (B, K, 3)
    b, f, k = local.shape[:3]
    mu = geometry.forward_kinematics(
        lerped[..., root, :3].reshape(-1, 3),
        local.reshape(-1, k, 3, 3),
        jnp.broadcast_to(offsets[:, None], (b, f, k, 3)).reshape(-1, k, 3),
        model.parents,
        model.order,
    ).reshape(b, f, k, 3)
    inner = jnp.concatenate([mu, lerped[..., 3:]], axis=-1)
    return jnp.concatenate([x_start[:, None], inner[:, 1:-1], x_end[:, None]], axis=1)


# --- compiled entry points (the model is split once; graphdef is static) ---------------------


@functools.partial(jax.jit, static_argnames=("graphdef", "num_frames", "num_samples"))
def generate_jit(graphdef, state, x_cond, key, *, num_frames: int, num_samples: int):
    """`generate_motion` on a split model (nnx.split)."""
    return generate_motion(nnx.merge(graphdef, state), x_cond, num_frames, key, num_samples)


@functools.partial(jax.jit, static_argnames=("graphdef", "gap", "num_trajectories"))
def interpolate_jit(graphdef, state, x_start, x_end, key, *, gap: int, num_trajectories: int):
    """`interpolate_motion` on a split model."""
    model = nnx.merge(graphdef, state)
    return interpolate_motion(model, x_start, x_end, gap, key, num_trajectories)


@functools.partial(jax.jit, static_argnames=("graphdef", "gap"))
def slerp_jit(graphdef, state, x_start, x_end, key, *, gap: int):
    """`slerp_keypoints` on a split model."""
    return slerp_keypoints(nnx.merge(graphdef, state), x_start, x_end, gap, key)


@functools.partial(jax.jit, static_argnames=("graphdef",))
def infer_rotations_jit(graphdef, state, x, key):
    """`infer_rotations` on a split model."""
    return infer_rotations(nnx.merge(graphdef, state), x, key)


# --- retargeting (Eqs. 24-25, appendix A.4 and D.4) -----------------------------------------


def retarget_joints(
    root_positions: jax.Array,
    local_rotations: jax.Array,
    directions: jax.Array,
    target_joints: jax.Array,
    parents: tuple[int, ...],
    order: tuple[int, ...],
) -> tuple[jax.Array, jax.Array]:
    """Eqs. 24-25: the source's local rotations on the target's bones.

    mu^re_k,t = mu^re_parent(k),t + R^src_k,t d^tar_k with d^tar_k = d-bar_k ||mu^tar_k -
    mu^tar_parent(k)|| (Eq. 25), R^src the global rotations accumulated from the source's local
    rotations along the tree (Eq. 2).

    Args:
      root_positions: (T, 3) root trajectory of the retargeted motion.
      local_rotations: (T, K, 3, 3) source local rotations.
      directions: (K, 3) the offset directions d-bar_k shared by source and target.
      target_joints: (K, 3) target joint positions (one pose).
      parents, order: the skeleton (static).

    Returns:
      joint positions (T, K, 3) and global rotations (T, K, 3, 3).
    """
    offsets = geometry.bone_offsets(target_joints, parents, directions)  # (K, 3), Eq. 25
    return geometry.forward_kinematics_with_rotations(
        root_positions, local_rotations, offsets, parents, order
    )


def align_rotation(u: jax.Array, v: jax.Array) -> jax.Array:
    """The smallest rotation taking unit vectors u to v: (..., 3), (..., 3) -> (..., 3, 3).

    Rodrigues' formula about u x v; antiparallel inputs turn by pi about an axis normal to u.
    """
    u, v = geometry.normalize(u), geometry.normalize(v)
    c = jnp.sum(u * v, axis=-1)[..., None, None]
    axis = jnp.cross(u, v)
    # For u = -v any axis normal to u works: u x e_x, or u x e_y when u is along x.
    fallback = jnp.cross(u, jnp.where(jnp.abs(u[..., :1]) < 0.9, jnp.eye(3)[0], jnp.eye(3)[1]))
    anti = (c[..., 0, 0] < -1.0 + 1e-6)[..., None]
    axis = jnp.where(anti, geometry.normalize(fallback), axis)
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    zero = jnp.zeros_like(x)
    skew = jnp.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(*x.shape, 3, 3)
    eye = jnp.eye(3)
    general = eye + skew + skew @ skew / (1.0 + jnp.where(anti[..., None], 0.0, c))
    flip = 2.0 * axis[..., :, None] * axis[..., None, :] - eye  # rotation by pi about `axis`
    return jnp.where(anti[..., None], flip, general)


def rest_rotations(
    joints: jax.Array,
    rotations: jax.Array,
    directions: jax.Array,
    parents: tuple[int, ...],
) -> jax.Array:
    """Global rotations of a pose made consistent with its joints: R_k d-bar_k || mu_k - mu_p.

    An estimate R_k (e.g. the model's posterior rotations of the target) is corrected by the
    smallest rotation turning R_k d-bar_k onto the observed bone direction mu_k - mu_parent(k),
    keeping the estimate's twist about the bone; the root keeps its estimate. With these, a
    point on bone k that moves with joint k's transform stays on the retargeted bone.

    Args:
      joints: (K, 3) joint positions of the pose.
      rotations: (K, 3, 3) estimated global rotations.
      directions: (K, 3) d-bar_k.
      parents: (K,) the skeleton.

    Returns:
      (K, 3, 3) global rotations.
    """
    par = np.asarray(parents)
    bones = joints - joints[par]
    predicted = jnp.einsum("kij,kj->ki", rotations, geometry.normalize(directions))
    fix = align_rotation(predicted, bones)
    is_root = jnp.asarray(par == np.arange(len(par)))[:, None, None]
    return jnp.where(is_root, rotations, fix @ rotations)


def retarget_vertices(
    vertices: jax.Array,
    weights: jax.Array,
    rest_joints: jax.Array,
    rest_rots: jax.Array,
    joints: jax.Array,
    rotations: jax.Array,
) -> jax.Array:
    """Linear blend skinning of a target mesh onto a retargeted motion (appendix A.4).

    Joint k's transform maps the rest pose to frame t: v -> G_k,t G_k,rest^T (v - mu_k,rest) +
    mu_k,t, so a vertex fully bound to k moves rigidly with k's bone.

    Args:
      vertices: (V, 3) target mesh in its rest pose.
      weights: (V, K) skin weights (Algorithm 2).
      rest_joints, rest_rots: (K, 3), (K, 3, 3) the target's joints and global rotations.
      joints, rotations: (T, K, 3), (T, K, 3, 3) retargeted joints and global rotations.

    Returns:
      (T, V, 3) deformed vertices.
    """
    from nmjax.skeleton import linear_blend_skinning

    rel = rotations @ jnp.swapaxes(rest_rots, -1, -2)  # (T, K, 3, 3)
    trans = joints - jnp.einsum("tkij,kj->tki", rel, rest_joints)
    return linear_blend_skinning(vertices, weights, rotations=rel, translations=trans)


def retarget_mesh(
    vertices: jax.Array,
    weights: jax.Array,
    target_joints: jax.Array,
    target_rotations: jax.Array,
    source_rotations: jax.Array,
    source_root: jax.Array,
    directions: jax.Array,
    parents: tuple[int, ...],
    order: tuple[int, ...],
) -> tuple[jax.Array, jax.Array]:
    """The source motion on the target's bones, skinned onto the target mesh (`run_retarget`).

    The target's rest rotations are the global rotations of its own inferred local rotations,
    corrected onto its bones (`rest_rotations`). The retargeted root starts at the target's root
    and follows the source root's displacement from its first frame; Eqs. 24-25 give the joints
    (`retarget_joints`) and LBS the vertices (`retarget_vertices`). Frame t is the target in the
    source's pose t, so when the source starts in the target's own pose (its first rotations
    are the target's and reproduce the target's bones), frame 0 is the target mesh as given.

    Args:
      vertices: (V, 3) target mesh; weights: (V, K) its skin weights (Algorithm 2).
      target_joints: (K, 3) the target's joints; target_rotations: (K, 3, 3) the local rotations
        inferred for its pose.
      source_rotations: (T, K, 3, 3) source local rotations; source_root: (T, 3) its root path.
      directions: (K, 3) the offset directions d-bar_k.
      parents, order: the skeleton (static).

    Returns:
      deformed vertices (T, V, 3) and retargeted joints (T, K, 3).
    """
    rest, joints, rotations = retarget_pose(
        target_joints,
        target_rotations,
        source_rotations,
        source_root,
        directions,
        parents,
        order,
    )
    return retarget_vertices(vertices, weights, target_joints, rest, joints, rotations), joints


def retarget_pose(
    target_joints: jax.Array,
    target_rotations: jax.Array,
    source_rotations: jax.Array,
    source_root: jax.Array,
    directions: jax.Array,
    parents: tuple[int, ...],
    order: tuple[int, ...],
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The joint transforms of `retarget_mesh`: the target's rest rotations and the retargeted
    motion's joints and global rotations (arguments as there).

    Returns:
      rest global rotations (K, 3, 3), joints (T, K, 3) and global rotations (T, K, 3, 3); LBS
      moves joint k's part of the mesh by v -> R_k,t R_k,rest^T (v - mu_k,rest) + mu_k,t.
    """
    root = order[0]
    _, pose = retarget_joints(
        target_joints[root][None], target_rotations[None], directions, target_joints, parents, order
    )
    rest = rest_rotations(target_joints, pose[0], directions, parents)
    path = target_joints[root] + source_root - source_root[:1]
    joints, rotations = retarget_joints(
        path, source_rotations, directions, target_joints, parents, order
    )
    return rest, joints, rotations


# --- meshes ---------------------------------------------------------------------------------


def load_mesh(path: str | os.PathLike):
    """Reads a target mesh (.obj, .ply, .off, .stl, ... anything trimesh reads) and checks it.

    Watertight or not, one mesh or a scene (concatenated). Raises:
      FileNotFoundError: no such file.
      ValueError naming the file: unreadable, no vertices or faces, NaN / inf vertices.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"target mesh {path} does not exist (--target)")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as err:  # trimesh raises many types for broken files
        raise ValueError(
            f"cannot read target mesh {path} ({type(err).__name__}: {err}); give an .obj, .ply, "
            ".off or .stl mesh with vertices and faces"
        ) from err
    vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), np.float64)
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))))
    if vertices.ndim != 2 or len(vertices) == 0:
        raise ValueError(f"target mesh {path} has no vertices; give a non-empty mesh")
    if not np.all(np.isfinite(vertices)):
        bad = int(np.sum(~np.all(np.isfinite(vertices), axis=1)))
        raise ValueError(
            f"target mesh {path} has {bad} vertices with NaN or inf coordinates; repair the file"
        )
    if faces.ndim != 2 or len(faces) == 0:
        raise ValueError(
            f"target mesh {path} has no faces (a point cloud?); retargeting samples points on the "
            "surface and needs a triangle mesh"
        )
    if float(np.sum(mesh.area_faces)) <= 0.0:
        raise ValueError(f"target mesh {path} has zero surface area; give a non-degenerate mesh")
    return mesh


def sample_mesh_points(mesh, count: int, seed: int = 0) -> np.ndarray:
    """(count, 3) float32 points sampled uniformly on the mesh surface (fixed seed)."""
    import trimesh

    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(points, np.float32)


def normalization_of(points: np.ndarray) -> tuple[np.ndarray, float]:
    """(bmin (3,), scale) of DESIGN section 4: p' = scale (p - bmin) - 1 for one pose."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    bmin = points.min(axis=0)
    scale = 2.0 / (float(np.max(points.max(axis=0) - bmin)) + 1e-5)
    return bmin, scale


# --- a motion from a point-sequence file (`--source-file`) -----------------------------------


def load_point_sequence(path: str | os.PathLike) -> np.ndarray:
    """Reads a point-sequence file: a NumPy .npy of shape (T, N, >= 3), xyz first (the format
    of the authors' data/demo/source/*.npy; further columns such as normals are dropped).

    Returns:
      (T, N, 3) float32.

    Raises:
      FileNotFoundError: no such file.
      ValueError naming the file: not a .npy array, another shape, NaN / inf coordinates.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"point-sequence file {path} does not exist (--source-file)")
    try:
        points = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as err:
        raise ValueError(
            f"cannot read {path} as a NumPy .npy array ({' '.join(str(err).split())}); give a "
            "(T, N, 3) point sequence saved with numpy.save"
        ) from err
    if points.ndim != 3 or points.shape[-1] < 3 or 0 in points.shape:
        raise ValueError(
            f"{path} holds an array of shape {points.shape}; a point sequence is (T frames, N "
            "points, >= 3 coordinates)"
        )
    points = np.asarray(points[..., :3], np.float32)
    if not np.all(np.isfinite(points)):
        raise ValueError(f"{path} has NaN or inf coordinates; repair the file")
    return points


def point_file_keypoints(
    detector: runs.Detector, path: str | os.PathLike, frames: int, sample_rate: int
) -> tuple[np.ndarray, np.ndarray]:
    """A point-sequence file's motion as the release's demos take it: `frames` frames from the
    first, every `sample_rate`-th, normalised with one bounding box over them (DESIGN section
    4, the release's episodic normalisation), voxelised, and run through the detector as one
    crop (its spatio-temporal branch sees their mean).

    Args:
      detector: the phase-1 detector.
      path: a (T, N, >= 3) .npy (`load_point_sequence`).
      frames: F, the crop length.
      sample_rate: the frame step.

    Returns:
      keypoints (F, K, 4) and voxels (F, G, G, G).

    Raises:
      ValueError: the file has fewer than (F - 1) sample_rate + 1 frames.
    """
    from nmjax.data.voxelize import normalize_sequence, voxelize

    points = load_point_sequence(path)
    span = (frames - 1) * sample_rate + 1
    if len(points) < span:
        raise ValueError(
            f"{path} has {len(points)} frames; {frames} frames every {sample_rate} need {span} "
            "(ask for fewer frames or a smaller --source-rate)"
        )
    clip, _ = normalize_sequence(points[:span:sample_rate])
    voxels = voxelize(clip, detector.cfg.data.grid)
    # One crop: a batch of one instead of the training batch the detector pads to.
    one = dataclasses.replace(
        detector.cfg, data=dataclasses.replace(detector.cfg.data, batch_size=1)
    )
    single = runs.Detector(detector.run, one, detector.graphdef, detector.state)
    return single.keypoints(voxels[None])[0], voxels


def source_file_clip(
    skel_run: Path, path: str | os.PathLike, frames: int, sample_rate: int | None
) -> tuple[str, np.ndarray, np.ndarray]:
    """(name, keypoints (1, F, K, 4), first voxel frame (1, G, G, G)) of `point_file_keypoints`
    with the phase-1 run's detector; `sample_rate` None takes the run's."""
    detector = runs.Detector.load(skel_run)
    rate = detector.cfg.data.sample_rate if sample_rate is None else sample_rate
    keypoints, voxels = point_file_keypoints(detector, path, frames, rate)
    return Path(path).stem, keypoints[None].astype(np.float32), voxels[None, 0]


# --- on run folders: the task commands (`nmjax generate`, `interpolate`, `retarget`) ----------
#
# Inputs are test sequences of the phase-1 run, as the phase-2 run was fed (its `inputs`):
# "crop" runs the phase-1 detector on each clip normalised with its own bounding box, as the
# release's generation and interpolation demos do; "sequence" cuts the clips from the
# whole-sequence keypoints_test.npz (`run_retarget` always does). Each writes into `out` (default
# `RUN/<command>`): the keypoints as .npz, a GIF of the motion and a PNG strip of frames;
# `run_retarget` also writes one .obj per frame.


def pick_inputs(
    trajectories: dict[str, np.ndarray], count: int, frames: int, names: list[str] | None = None
) -> tuple[list[str], np.ndarray]:
    """The first `count` sequences (sorted names, or `names`), frames 0..frames-1 of each.

    Sequences shorter than `frames` are padded with their last frame. Returns (names, (I, F, K, 4)).
    """
    chosen = sorted(trajectories) if names is None else names
    missing = [n for n in chosen if n not in trajectories]
    if missing:
        raise ValueError(f"no test sequence named {missing}; available: {sorted(trajectories)}")
    chosen = chosen[:count]
    crops = [pad_with_last(trajectories[name][:frames], frames) for name in chosen]
    return chosen, np.stack(crops).astype(np.float32)


@dataclasses.dataclass
class TaskClips:
    """Observed test clips of a task command, in the coordinates the model is conditioned in.

    Attributes:
      names: the sequences, one clip each (from frame 0).
      keypoints: (I, F, K, 4) the clips' keypoints.
      real_frames: (I,) frames of each clip the sequence really has (the rest repeats its last).
      first_voxels: (I, G, G, G) each clip's first voxel frame, when asked for (decoding).
    """

    names: list[str]
    keypoints: np.ndarray
    real_frames: np.ndarray
    first_voxels: np.ndarray | None = None


def generation_clips(
    cfg: DynTrainConfig, skel_run: Path, count: int, cond: int, gen: int, voxels: bool = False
) -> TaskClips:
    """Frames 0 .. cond + gen - 1 of the first `count` test sequences, conditioned as trained.

    "sequence": cut from keypoints_test.npz. "crop" (the release's generation): the clip is
    normalised with the bounding box of its first crop (max(T, cond) frames, T = `cfg.frames`)
    and voxelised; the conditioning keypoints, keypoints[:, :cond], are its first `cond` frames
    run through the detector on their own; the frames after them (the true continuation) are
    detected in consecutive windows of T frames in the same coordinates.

    Args:
      cfg: the phase-2 run's DynTrainConfig.
      skel_run: its phase-1 run.
      count, cond, gen: clips, conditioning frames, generated frames.
      voxels: also return each clip's first voxel frame.
    """
    total = cond + gen
    if cfg.inputs == "sequence":
        trajectories = runs.load_trajectories(skel_run, "test")
        names, observed = pick_inputs(trajectories, count, total)
        real = np.array([min(len(trajectories[n]), total) for n in names], np.int32)
        first = None
        if voxels:
            detector = runs.Detector.load(skel_run)
            seqs, data = runs.split_sequences(detector, "test"), detector.cfg.data
            first = np.stack(
                [runs.sequence_voxels(seqs[n], data.sample_rate, data.grid)[0] for n in names]
            )
        return TaskClips(names, observed, real, first)
    detector = runs.phase2_detector(skel_run)
    seqs, data = runs.split_sequences(detector, "test"), detector.cfg.data
    names = sorted(seqs)[:count]
    box = max(cfg.frames, cond)
    real = np.array([min(-(-seqs[n].num_frames // data.sample_rate), total) for n in names])
    observed, first = [], []
    for name, frames in zip(names, real, strict=True):
        vox = runs.clip_voxels(seqs[name], 0, max(total, box), data, box_frames=box)[:total]
        x_cond = detector.keypoints(vox[None, :cond])[0]
        rest = detector.keypoints(runs.sequence_windows(vox, cfg.frames))
        rest = rest.reshape(-1, *rest.shape[2:])[:total]
        clip = np.concatenate([x_cond, rest[cond:]])
        clip[frames:] = clip[frames - 1]  # past the sequence's end the last real frame is held
        observed.append(clip)
        first.append(vox[0])
    return TaskClips(
        names,
        np.stack(observed).astype(np.float32),
        real.astype(np.int32),
        np.stack(first) if voxels else None,
    )


def interpolation_clips(cfg: DynTrainConfig, skel_run: Path, count: int, gap: int) -> TaskClips:
    """Frames 0 .. gap of the first `count` test sequences: the keyframes and the truth between.

    "sequence": cut from keypoints_test.npz. "crop": a clip of max(T, gap + 1) frames from frame
    0, normalised with its own bounding box and run through the detector as one crop (its first
    gap + 1 frames kept), as the release's interpolation takes its keyframes.
    """
    if cfg.inputs == "sequence":
        trajectories = runs.load_trajectories(skel_run, "test")
        names, truth = pick_inputs(trajectories, count, gap + 1)
        real = np.array([min(len(trajectories[n]), gap + 1) for n in names], np.int32)
        return TaskClips(names, truth, real)
    detector = runs.phase2_detector(skel_run)
    seqs, rate = runs.split_sequences(detector, "test"), detector.cfg.data.sample_rate
    names = sorted(seqs)[:count]
    clips = [(seqs[n], 0) for n in names]
    truth = runs.detect_clips(detector, clips, max(cfg.frames, gap + 1))[:, : gap + 1]
    real = [min(-(-seqs[n].num_frames // rate), gap + 1) for n in names]
    return TaskClips(names, truth, np.array(real, np.int32))


@dataclasses.dataclass
class Interpolators:
    """The compiled interpolation methods on one phase-2 model (and the optional VRNN)."""

    nm: tuple[Any, Any]  # (graphdef, state) of the "nm" dynamics
    vrnn: tuple[Any, Any] | None
    trajectories: int

    def run(self, method: str, x_start, x_end, gap: int, key) -> np.ndarray:
        """(B, gap + 1, K, 4) keypoints of `method` between keyframes (B, K, 4)."""
        x_start, x_end = jnp.asarray(x_start), jnp.asarray(x_end)
        if method == "Lerp":
            return np.asarray(lerp_keypoints(x_start, x_end, gap))
        if method == "Slerp":
            return np.asarray(slerp_jit(*self.nm, x_start, x_end, key, gap=gap))
        model = self.nm if method == "Ours" else self.vrnn
        if model is None:
            raise ValueError(f"no model for method {method!r}")
        return np.asarray(
            interpolate_jit(
                *model, x_start[:, None], x_end, key, gap=gap, num_trajectories=self.trajectories
            )
        )


# --- generate -------------------------------------------------------------------------------


def rig_arrays(skel_run: Path, num_keypoints: int) -> dict[str, np.ndarray]:
    """What `nmjax export` needs beside a task's motions: "frame_rate" and "up_axis" of the
    phase-1 run's sequences and "keep", the (K,) nodes its skeleton keeps."""
    frame_rate, up_axis = runs.motion_format(skel_run)
    kept = runs.pruned_skeleton(skel_run)
    return {
        "frame_rate": np.float64(frame_rate),
        "up_axis": np.int64(up_axis),
        "keep": np.ones(num_keypoints, bool) if kept is None else kept[1],
    }


def run_generate(
    run: str | Path,
    *,
    cond: int = 5,
    gen: int = 25,
    samples: int = 3,
    inputs: int = 2,
    seed: int = 0,
    voxels: bool = False,
    out: str | Path | None = None,
    source_file: str | Path | None = None,
    source_rate: int | None = None,
) -> Path:
    """Motion generation for the first `inputs` test sequences; returns the output folder.

    With `source_file` the one input is instead the first `cond` frames (every `source_rate`-th,
    default the run's sample rate) of that point-sequence file, detected as the release's
    generation demo does (`point_file_keypoints`); its observed motion holds the last of them.

    The observed frames are taken as the run was trained (`generation_clips`) and inferred with
    the model's best-of-S posterior samples. Writes generate.npz (keypoints (I, S, T_cond +
    T_gen, K, 4), each sample starting with the T_cond observed frames; observed (I, T, K, 4) -
    those and the true continuation, padded with its last frame where the sequence is shorter
    (long horizons) - observed_frames (I,) the real frames of it, names, parents), optionally
    voxels.npz (decoded occupancy of every sample, uint8), and per input a GIF and PNG strip
    (observed next to the samples).
    """
    from nmjax import viz  # matplotlib only where a picture is drawn

    model, cfg, skel_run = runs.load_phase2(run)
    out = Path(out) if out is not None else Path(run) / "generate"
    if source_file is not None:
        name, x_cond, first = source_file_clip(skel_run, source_file, cond, source_rate)
        held = np.concatenate([x_cond, np.repeat(x_cond[:, -1:], gen, axis=1)], axis=1)
        clips = TaskClips([name], held, np.array([cond], np.int32), first)
    else:
        clips = generation_clips(cfg, skel_run, inputs, cond, gen, voxels=voxels)
    names, observed, real_frames = clips.names, clips.keypoints, clips.real_frames
    graphdef, state = nnx.split(model)
    keypoints, _ = generate_jit(
        graphdef,
        state,
        jnp.asarray(observed[:, :cond]),
        jax.random.key(seed),
        num_frames=gen,
        num_samples=samples,
    )
    keypoints = np.asarray(keypoints)
    atomic.save_npz(
        out / "generate.npz",
        keypoints=keypoints,
        observed=observed,
        observed_frames=real_frames,
        names=np.array(names),
        parents=np.array(model.parents),
        cond=np.int32(cond),
        **rig_arrays(skel_run, len(model.parents)),
    )
    if voxels:
        detector = runs.Detector.load(skel_run)
        decoded = [detector.decode(keypoints[:, s], clips.first_voxels) for s in range(samples)]
        atomic.save_npz(out / "voxels.npz", voxels=(np.stack(decoded, 1) >= 0.5).astype(np.uint8))
    for i, name in enumerate(names):
        motions = [observed[i]] + [keypoints[i, s] for s in range(samples)]
        held = real_frames[i] < cond + gen  # the sequence ends before the horizon
        labels = [f"observed (held from {real_frames[i]})" if held else "observed"]
        labels += [f"sample {s}" for s in range(samples)]
        viz.write_motion_pictures(out / name, motions, labels, model.parents)
    return out


# --- interpolate ----------------------------------------------------------------------------


def run_interpolate(
    run: str | Path,
    *,
    gap: int = 10,
    trajectories: int = 16,
    inputs: int = 2,
    vrnn_run: str | Path | None = None,
    seed: int = 0,
    out: str | Path | None = None,
    source_file: str | Path | None = None,
    source_rate: int | None = None,
) -> Path:
    """Interpolation between frames 0 and `gap` of the first `inputs` test sequences.

    With `source_file` the one input is instead the first gap + 1 frames (every `source_rate`-th,
    default the run's sample rate) of that point-sequence file, detected as one crop as the
    release's interpolation demo does (`point_file_keypoints`).

    The keyframes and the truth between them are taken as the run was trained
    (`interpolation_clips`). Writes interpolate.npz ({method: (I, gap + 1, K, 4)}, "truth", names,
    parents) and per input a GIF and PNG strip with one panel per method and the truth.
    """
    from nmjax import viz  # matplotlib only where a picture is drawn

    model, cfg, skel_run = runs.load_phase2(run)
    out = Path(out) if out is not None else Path(run) / "interpolate"
    if vrnn_run is not None:
        runs.phase2_runs(Path(run), vrnn_run)  # refuses a baseline of another skeleton or input
    if source_file is not None:
        name, truth, _ = source_file_clip(skel_run, source_file, gap + 1, source_rate)
        names = [name]
    else:
        clips = interpolation_clips(cfg, skel_run, inputs, gap)
        names, truth = clips.names, clips.keypoints
    vrnn = None if vrnn_run is None else nnx.split(runs.restore_dynamics(vrnn_run))
    interp = Interpolators(nnx.split(model), vrnn, trajectories)
    methods = ["Ours"] + (["VRNN"] if vrnn is not None else []) + ["Lerp", "Slerp"]
    key = jax.random.key(seed)
    results = {m: interp.run(m, truth[:, 0], truth[:, -1], gap, key) for m in methods}
    atomic.save_npz(
        out / "interpolate.npz",
        truth=truth,
        names=np.array(names),
        parents=np.array(model.parents),
        **results,
        **rig_arrays(skel_run, len(model.parents)),
    )
    for i, name in enumerate(names):
        motions = [truth[i]] + [results[m][i] for m in methods]
        viz.write_motion_pictures(out / name, motions, ["truth", *methods], model.parents)
    return out


# --- retarget -------------------------------------------------------------------------------


def detect_target_joints(detector: runs.Detector, points: np.ndarray) -> np.ndarray:
    """Keypoints (K, 4) of one normalised point cloud, the frame repeated over a T-frame crop."""
    from nmjax.data.voxelize import voxelize

    cfg = detector.cfg
    grid = voxelize(points, cfg.data.grid)
    crop = np.broadcast_to(grid, (1, cfg.data.frames, *grid.shape))
    keypoints, _ = detector.run_batches(np.ascontiguousarray(crop))
    return keypoints[0, 0]


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """A triangle mesh as Wavefront .obj text, atomically."""
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    atomic.write_text(path, "\n".join(lines) + "\n")


RETARGET_FILE = "retarget.npz"  # the keypoints and joints of a `run_retarget` output folder
RETARGET_FRAME = "frame_{:04d}.obj"  # its posed target meshes, one per frame


def run_retarget(
    run: str | Path,
    target: str | Path,
    *,
    source: str | None = None,
    frames: int = 30,
    points: int = 20000,
    seed: int = 0,
    out: str | Path | None = None,
    source_file: str | Path | None = None,
    source_rate: int | None = None,
) -> Path:
    """Retargets a test motion of the run onto a target mesh (Fig. 6, appendix D.4).

    The source motion is the test sequence `source` (default the first), or with `source_file`
    the first `frames` frames (every `source_rate`-th, default the run's sample rate) of that
    point-sequence file, detected as one crop as the release's retargeting demo does
    (`point_file_keypoints`; the demo takes 40 frames at rate 1).

    1. Target skeleton: `points` surface samples of the mesh, normalised (DESIGN section 4),
       voxelised, keypoints by the phase-1 detector; topology = the run's skeleton.
    2. Source motion: local rotations and root trajectory inferred by the dynamics posterior
       (best of S) from the source keypoints.
    3. Eqs. 24-25 give the retargeted joints; target rest rotations are the posterior's rotations
       of the target pose, corrected onto its bones (`rest_rotations`).
    4. Skin weights (Algorithm 2, the run's keypoint intensities for pruning) and LBS (steps 3-4
       are `retarget_mesh`); the result is mapped back to the mesh's units and written as
       frame_XXXX.obj plus a GIF.

    Returns:
      the output folder.
    """
    from nmjax import viz  # matplotlib only where a picture is drawn
    from nmjax.skeleton import skin_weights

    mesh = load_mesh(target)
    model, cfg, skel_run = runs.load_phase2(run)
    out = Path(out) if out is not None else Path(run) / f"retarget-{Path(target).stem}"
    if source_file is not None:
        if source is not None:
            raise ValueError("give either --source NAME or --source-file PATH, not both")
        name, x_src, _ = source_file_clip(skel_run, source_file, frames, source_rate)
    else:
        trajectories = runs.load_trajectories(skel_run, "test")
        names = None if source is None else [source]
        (name,), x_src = pick_inputs(trajectories, 1, frames, names)
    skeleton = runs.read_skeleton(skel_run)
    intensities = runs.skeleton_intensities(skel_run)

    # Target pose in its own normalised frame.
    bmin, scale = normalization_of(mesh.vertices)
    cloud = (sample_mesh_points(mesh, points, seed) - bmin) * scale - 1.0
    detector = runs.Detector.load(skel_run)
    target_kp = detect_target_joints(detector, cloud.astype(np.float32))
    vertices = (np.asarray(mesh.vertices) - bmin) * scale - 1.0

    graphdef, state = nnx.split(model)
    key_src, key_tar = jax.random.split(jax.random.key(seed))
    src_rot, src_rec = infer_rotations_jit(graphdef, state, jnp.asarray(x_src), key_src)
    tar_in = jnp.asarray(np.repeat(target_kp[None, None], 2, axis=1))
    tar_rot, _ = infer_rotations_jit(graphdef, state, tar_in, key_tar)
    parents, order, root = model.parents, model.order, model.order[0]
    weights = skin_weights(vertices, target_kp[:, :3], skeleton, intensities=intensities)
    rest, joints, rotations = retarget_pose(
        jnp.asarray(target_kp[:, :3]),
        tar_rot[0, 0],
        src_rot[0],
        src_rec[0, :, root, :3],
        model.directions[...],
        parents,
        order,
    )
    moved = retarget_vertices(
        jnp.asarray(vertices, jnp.float32),
        jnp.asarray(weights),
        jnp.asarray(target_kp[:, :3]),
        rest,
        joints,
        rotations,
    )

    def to_mesh(x) -> np.ndarray:  # the normalised frame back to the mesh's units
        return (np.asarray(x, np.float64) + 1.0) / scale + bmin

    moved_mesh = to_mesh(moved)
    faces = np.asarray(mesh.faces)
    for t, verts in enumerate(moved_mesh):
        write_obj(out / RETARGET_FRAME.format(t), verts, faces)
    src_mu = np.asarray(x_src[0])
    atomic.save_npz(
        out / RETARGET_FILE,
        source_keypoints=src_mu,
        target_keypoints=target_kp,
        joints=to_mesh(joints).astype(np.float32),
        skin_weights=weights,
        parents=np.array(parents),
        source=np.array(name),
        # The rig (`nmjax export`): LBS moves joint k's part of the mesh rigidly from its rest
        # transform (rest_rotations, rest_joints) to its transform at t (rotations, joints).
        rotations=np.asarray(rotations, np.float32),
        rest_rotations=np.asarray(rest, np.float32),
        rest_joints=to_mesh(target_kp[:, :3]).astype(np.float32),
        rest_vertices=np.asarray(mesh.vertices, np.float32),
        faces=faces.astype(np.int64),
        **rig_arrays(skel_run, len(parents)),
    )
    # Pictures in the normalised frames (source and target each in their own [-1, 1] cube).
    sub = np.random.default_rng(seed).choice(len(faces), min(len(faces), 1500), replace=False)
    tri_centres = np.asarray(moved)[:, faces[sub]].mean(axis=2)  # (T, P, 3) a surface sketch
    viz.write_motion_pictures(
        out / "retarget",
        [src_mu, np.asarray(joints)],
        [f"source {name}", f"retargeted {Path(target).name}"],
        parents,
        clouds=[None, tri_centres],
    )
    return out


def read_retarget(folder: str | Path) -> dict[str, Any]:
    """A `run_retarget` output folder read back (the one reader of that format).

    Returns:
      {"vertices": (T, V, 3) float32 posed target meshes in the mesh's units, "faces": (F, 3),
      "joints": (T, K, 3) retargeted joints in the mesh's units, "parents": (K,),
      "source_keypoints": (T, K, 4) the source motion in its normalised frame, "source": name}.

    Raises:
      FileNotFoundError: no such folder, or one without retarget.npz or frame meshes (names the
        command that writes them).
      ValueError: frames that disagree with each other or with retarget.npz.
    """
    import trimesh

    folder = Path(folder)
    fix = "write it with `nmjax retarget --run RUN --target MESH --out DIR`"
    if not folder.is_dir():
        raise FileNotFoundError(f"retarget output folder {folder} does not exist; {fix}")
    frames = sorted(folder.glob(RETARGET_FRAME.replace("{:04d}", "[0-9]*")))
    if not (folder / RETARGET_FILE).is_file() or not frames:
        raise FileNotFoundError(
            f"{folder} lacks {RETARGET_FILE} or its {RETARGET_FRAME.format(0)}... meshes; is it "
            f"an unfinished retarget output? {fix}"
        )
    with np.load(folder / RETARGET_FILE) as z:
        missing = [k for k in ("joints", "parents", "source_keypoints", "source") if k not in z]
        if missing:
            raise ValueError(f"{folder / RETARGET_FILE} lacks {missing}; {fix}")
        out = {
            "joints": np.asarray(z["joints"], np.float32),
            "parents": np.asarray(z["parents"]),
            "source_keypoints": np.asarray(z["source_keypoints"], np.float32),
            "source": str(z["source"]),
        }
    meshes = [trimesh.load(path, force="mesh", process=False) for path in frames]
    faces = np.asarray(meshes[0].faces)
    if any(
        m.vertices.shape != meshes[0].vertices.shape or len(m.faces) != len(faces) for m in meshes
    ):
        raise ValueError(f"{folder}: the frame meshes differ in vertices or faces; {fix}")
    if len(meshes) != len(out["joints"]):
        raise ValueError(
            f"{folder}: {len(meshes)} frame meshes but {len(out['joints'])} frames of joints in "
            f"{RETARGET_FILE}; {fix}"
        )
    out["vertices"] = np.stack([np.asarray(m.vertices, np.float32) for m in meshes])
    out["faces"] = faces
    return out
