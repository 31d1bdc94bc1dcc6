"""Motion retargeting (Eqs. 24-25, appendix A.4 and D.4): source local rotations with target bone
offsets (`retarget_joints`), skin weights (Algorithm 2, `nmjax.skeleton.skin_weights`) and linear
blend skinning of a target mesh (`retarget_vertices`), together `retarget_mesh`; on a run folder
`run_retarget` (`nmjax retarget`), whose output folder `nmjax.tasks.outputs` writes and reads.
"""

from __future__ import annotations

import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from nmjax import geometry, run_folder
from nmjax.models.dynamics import Dynamics
from nmjax.tasks import outputs
from nmjax.tasks.inputs import pick_inputs, source_file_clip
from nmjax.train import trained


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


@functools.partial(jax.jit, static_argnames=("graphdef",))
def infer_rotations_jit(graphdef, state, x, key):
    """`infer_rotations` on a split model."""
    return infer_rotations(nnx.merge(graphdef, state), x, key)


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
    fix = geometry.align_rotation(predicted, bones)
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
    rel = rotations @ jnp.swapaxes(rest_rots, -1, -2)  # (T, K, 3, 3)
    trans = joints - jnp.einsum("tkij,kj->tki", rel, rest_joints)
    return geometry.linear_blend_skinning(vertices, weights, rotations=rel, translations=trans)


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


def detect_target_joints(detector: trained.Detector, points: np.ndarray) -> np.ndarray:
    """Keypoints (K, 4) of one normalised point cloud, the frame repeated over a T-frame crop."""
    from nmjax.data.voxelize import voxelize

    cfg = detector.cfg
    grid = voxelize(points, cfg.data.grid)
    crop = np.broadcast_to(grid, (1, cfg.data.frames, *grid.shape))
    keypoints, _ = detector.run_batches(np.ascontiguousarray(crop))
    return keypoints[0, 0]


def run_retarget(
    run: str | Path,
    target: str | Path,
    *,
    source: str | None = None,
    frames: int | None = None,
    points: int = 20000,
    seed: int = 0,
    out: str | Path | None = None,
    source_file: str | Path | None = None,
    source_rate: int | None = None,
) -> Path:
    """Retargets a test motion of the run onto a target mesh (Fig. 6, appendix D.4).

    The source motion is the first `frames` frames (None: every frame) of the test sequence
    `source` (default the first), or with `source_file` of that point-sequence file (every
    `source_rate`-th, default the run's sample rate), detected as one crop as the release's
    retargeting demo does (`point_file_keypoints`; the demo takes 40 frames at rate 1).

    1. Target skeleton: `points` surface samples of the mesh, normalised (docs/architecture.md §4),
       voxelised, keypoints by the phase-1 detector; topology = the run's skeleton.
    2. Source motion: local rotations and root trajectory inferred by the dynamics posterior
       (best of S) from the source keypoints.
    3. Eqs. 24-25 give the retargeted joints; target rest rotations are the posterior's rotations
       of the target pose, corrected onto its bones (`rest_rotations`).
    4. Skin weights (Algorithm 2, the run's keypoint intensities for pruning) and LBS (steps 3-4
       are `retarget_mesh`); the result is mapped back to the mesh's units and written as
       frame_XXXX.obj and retarget.npz (`outputs.write_retarget`) plus a GIF.

    Returns:
      the output folder.
    """
    from nmjax import viz  # matplotlib only where a picture is drawn
    from nmjax.data.meshes import load_mesh, sample_surface
    from nmjax.data.normalize import apply_box, normalization_box, undo_box
    from nmjax.skeleton import skin_weights

    if run_folder.run_kind(run) == "skel":
        raise ValueError(
            f"--run {run} is a phase-1 run (nmjax train-skel); retarget needs a phase-2 run "
            f"trained on it (nmjax train-dyn --skel-run {run}); `nmjax rig --from RAW` makes a "
            "rig in one command"
        )
    mesh = load_mesh(target)
    model, cfg, skel_run = trained.load_phase2(run)
    out = Path(out) if out is not None else Path(run) / f"retarget-{Path(target).stem}"
    if source_file is not None:
        if source is not None:
            raise ValueError("give either --source NAME or --source-file PATH, not both")
        name, x_src, _ = source_file_clip(skel_run, source_file, frames, source_rate)
    else:
        trajectories = run_folder.load_trajectories(skel_run, "test")
        names = None if source is None else [source]
        (name,), x_src = pick_inputs(trajectories, 1, frames, names)
    skeleton = run_folder.read_skeleton(skel_run)
    intensities = run_folder.skeleton_intensities(skel_run)

    # Target pose in its own normalised frame: the box of the mesh's vertices, one frame.
    bmin, scale = normalization_box(np.asarray(mesh.vertices)[None])
    bmin, scale = bmin[0, 0], scale[0, 0]  # (3,) and (1,), to broadcast against (..., 3)
    cloud = apply_box(
        sample_surface(mesh.vertices, mesh.faces, points, seed, str(target)), bmin, scale
    )
    detector = trained.Detector.load(skel_run)
    target_kp = detect_target_joints(detector, cloud.astype(np.float32))
    vertices = apply_box(mesh.vertices, bmin, scale)

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
        return undo_box(x, bmin, scale)

    faces = np.asarray(mesh.faces)
    src_mu = np.asarray(x_src[0])
    outputs.write_retarget(
        out,
        outputs.rig_arrays(skel_run, len(parents)),
        to_mesh(moved),
        faces,
        source=name,
        source_keypoints=src_mu,
        target_keypoints=target_kp,
        joints=to_mesh(joints),
        skin_weights=weights,
        parents=parents,
        rotations=rotations,
        rest_rotations=rest,
        rest_joints=to_mesh(target_kp[:, :3]),
        rest_vertices=mesh.vertices,
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
