"""What `nmjax export` reads: a run folder or a task's output folder, turned into a `Rig` in the
data's axes (`load`).

- an `nmjax retarget` output: the retargeted joints with the skinned target mesh; rotations
  from the retargeting (Eqs. 24-25), rest pose the target mesh's;
- an `nmjax generate` output: one sample (`--sample`) of one input (`--seq`); an `nmjax
  interpolate` output: one method's motion (`--method`) of one input; a phase-1 run with
  `--seq`: the detector's keypoints of that sequence. These are positions only: rotations are
  swing only, from the bones (`rig.swing_rotations`); rest pose frame 0;
- a phase-2 run with `--seq`: the model's reconstruction of that sequence (best-of-S
  posterior) with the model's own rotations (Eq. 2); rest pose frame 0;
- a phase-1 run with `--seq` whose sequence `nmjax refine` refined: the refined skeleton instead
  of the keypoints (`refined_rig`: constant bone lengths, full rotations with twist, the refined
  rest pose), unless `--unrefined` asks for the keypoints.

Only the nodes the run's skeleton keeps (skeleton.json `keep`) become joints, each hanging off
its nearest kept ancestor.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from nmjax.export.rig import Rig, kept_tree, swing_rotations

RETARGET_RIG_KEYS = ("rotations", "rest_rotations", "rest_joints", "rest_vertices", "faces")
# The animation name of a refined sequence's rig: `<sequence>_refined`.
REFINED_SUFFIX = "_refined"


@dataclasses.dataclass(frozen=True)
class Options:
    """The choices of `nmjax export` that pick a motion (None: not given)."""

    seq: str | None = None
    sample: int | None = None
    method: str | None = None
    split: str = "test"
    seed: int = 0
    unrefined: bool = False  # a phase-1 run: the keypoints even where a refined skeleton is


def kind(folder: Path) -> str:
    """ "retarget", "generate", "interpolate", "skel" (phase-1 run) or "dyn" (phase-2 run), as
    `tasks.folder_kind` tells them apart.

    Raises:
      FileNotFoundError: no such folder, or one that holds none of these.
    """
    from nmjax import run_folder, tasks

    if not folder.is_dir():
        raise FileNotFoundError(
            f"--run {folder} does not exist; give a run folder (train-skel, train-dyn) or an "
            "output folder of `nmjax retarget`, `generate` or `interpolate`"
        )
    found = tasks.folder_kind(folder)
    if found is None:
        raise FileNotFoundError(
            f"--run {folder} holds no {run_folder.CONFIG_FILE}, {tasks.RETARGET_FILE}, "
            f"{tasks.GENERATE_FILE} or {tasks.INTERPOLATE_FILE}; is it an unfinished run or output?"
        )
    return found


def _refuse(options: Options, allowed: tuple[str, ...], what: str) -> None:
    """Refuses every option of `options` that `what` has no use for (one line naming it)."""
    for name in ("seq", "sample", "method"):
        if name not in allowed and getattr(options, name) is not None:
            raise ValueError(f"--{name} does not apply to {what}")


def load(folder: str | Path, options: Options) -> tuple[Rig, int]:
    """(the rig in the data's axes, the data's up axis 0/1/2) of `folder` (module docstring).

    Raises:
      FileNotFoundError, ValueError: one line naming the bad input and the fix.
    """
    folder = Path(folder)
    found = kind(folder)
    if options.unrefined and found != "skel":
        raise ValueError(
            f"--unrefined does not apply to {folder}: only a phase-1 run holds refined skeletons"
        )
    if found == "retarget":
        _refuse(options, (), f"{folder} (a retarget output is one motion)")
        return _retarget(folder)
    if found in ("generate", "interpolate"):
        allowed = ("seq", "sample") if found == "generate" else ("seq", "method")
        _refuse(options, allowed, f"{folder} (an `nmjax {found}` output)")
        return _task_output(folder, found, options)
    _refuse(options, ("seq",), f"{folder} (a run folder)")
    if options.seq is None:
        names = _sequences(folder, found, options.split)
        raise ValueError(
            f"{folder} is a phase-{1 if found == 'skel' else 2} run, which holds many "
            f"sequences; pick one with --seq NAME ({options.split} sequences: {_listed(names)})"
        )
    return _phase1(folder, options) if found == "skel" else _phase2(folder, options)


def _listed(names: list[str]) -> str:
    names = sorted(names)
    return ", ".join(names[:8]) + (f", ... ({len(names)} in all)" if len(names) > 8 else "")


def _sequences(folder: Path, found: str, split: str) -> list[str]:
    from nmjax import run_folder
    from nmjax.config import DynTrainConfig

    skel_run = (
        folder if found == "skel" else run_folder.load_config(folder, DynTrainConfig).skel_run
    )
    return list(run_folder.load_trajectories(skel_run, split))


def _pick(trajectories: dict[str, np.ndarray], options: Options, where: Path) -> np.ndarray:
    if options.seq not in trajectories:
        raise ValueError(
            f"--seq {options.seq!r} is not a {options.split} sequence of {where}; available: "
            f"{_listed(list(trajectories))}"
        )
    return trajectories[options.seq]


def positions_rig(
    name: str,
    keypoints: np.ndarray,
    parents: np.ndarray,
    keep: np.ndarray,
    frame_rate: float,
) -> Rig:
    """A rig from joint positions only: the kept joints, rest pose = frame 0 with identity
    rotations, swing-only rotations from the bones (`swing_rotations`).

    Args:
      name: the motion's name; keypoints: (T, K, >= 3); parents: (K,) the full tree; keep: (K,).
    """
    from nmjax.skeleton import skeleton_from_parents

    order = skeleton_from_parents(np.asarray(parents)).order
    joints, local = kept_tree(parents, np.asarray(order), keep)
    positions = np.asarray(keypoints, np.float64)[:, joints, :3]
    rest = positions[0]
    return Rig(
        name=name,
        joints=joints,
        parents=local,
        positions=positions,
        rotations=swing_rotations(positions, rest, local),
        rest_positions=rest,
        rest_rotations=np.broadcast_to(np.eye(3), (len(joints), 3, 3)).copy(),
        frame_rate=frame_rate,
    )


def kept_skin_weights(
    surface: np.ndarray, rest_keypoints: np.ndarray, parents: np.ndarray, keep: np.ndarray
) -> np.ndarray:
    """Algorithm 2's skin weights (`skeleton.skin_weights`) of a rest surface over the kept
    nodes of a tree, as columns of the kept joints of `positions_rig` (in its joint order).

    Args:
      surface: (V, 3) the rest surface; rest_keypoints: (K, >= 3) the keypoints of the rest
        pose; parents: (K,) the tree (full or pruned); keep: (K,) bool kept nodes.

    Returns:
      (V, J) weights, rows summing to 1.
    """
    from nmjax.skeleton import skeleton_from_parents, skin_weights

    tree = skeleton_from_parents(np.asarray(parents))
    # Intensities 1 on the kept nodes and 0 elsewhere, pruned at 0.5: Algorithm 2 prunes to
    # exactly the stored node set, whatever threshold the skeleton was extracted with.
    weights = skin_weights(
        surface,
        np.asarray(rest_keypoints)[:, :3],
        tree,
        intensities=np.asarray(keep, np.float32),
        threshold=0.5,
    )
    joints, _ = kept_tree(np.asarray(parents), np.asarray(tree.order), keep)
    return weights[:, joints]


def _input_index(names: list[str], seq: str | None, path: Path) -> int:
    if seq is None:
        return 0
    if seq not in names:
        raise ValueError(f"--seq {seq!r} is not an input of {path}; its inputs: {_listed(names)}")
    return names.index(seq)


def _task_output(folder: Path, found: str, options: Options) -> tuple[Rig, int]:
    from nmjax import tasks

    if found == "generate":
        z, path = tasks.read_generate(folder), folder / tasks.GENERATE_FILE
    else:
        z, path = tasks.read_interpolate(folder), folder / tasks.INTERPOLATE_FILE
    names = [str(n) for n in z["names"]]
    i = _input_index(names, options.seq, path)
    parents = np.asarray(z["parents"])
    rate, up, keep = tasks.rig_format(z, len(parents))
    if found == "generate":
        motions = z["keypoints"]  # (I, S, T, K, 4)
        sample = 0 if options.sample is None else options.sample
        count = motions.shape[1]
        if not 0 <= sample < count:
            raise ValueError(
                f"--sample {sample} is out of range: {path} holds {count} samples per input "
                f"(0..{count - 1})"
            )
        motion, name = motions[i, sample], f"{names[i]}_sample_{sample}"
    else:
        method = "Ours" if options.method is None else options.method
        present = [*tasks.interpolated_methods(z), "truth"]
        if method not in present:
            raise ValueError(
                f"--method {method!r} is not in {path}; its methods: {', '.join(present)}"
            )
        motion, name = z[method][i], f"{names[i]}_{method}"
    return positions_rig(name, motion, parents, keep, rate), up


def _retarget(folder: Path) -> tuple[Rig, int]:
    from nmjax import tasks
    from nmjax.skeleton import skeleton_from_parents

    arrays = tasks.read_retarget_arrays(folder)
    missing = [k for k in RETARGET_RIG_KEYS if k not in arrays]
    if missing:
        raise ValueError(
            f"{folder / tasks.RETARGET_FILE} lacks {', '.join(missing)}: it was written before "
            "`nmjax export` existed; run `nmjax retarget` again to write them"
        )
    parents = arrays["parents"]
    rate, up, keep = tasks.rig_format(arrays, len(parents))
    weights = arrays["skin_weights"].astype(np.float64)
    # Algorithm 2 prunes at its default threshold; a node the skeleton dropped at another
    # threshold but the weights use is exported too, so the mesh moves as nmjax moved it.
    keep = keep | (weights.sum(axis=0) > 0)
    order = np.asarray(skeleton_from_parents(parents).order)
    joints, local = kept_tree(parents, order, keep)
    rig = Rig(
        name=f"{arrays['source']}_retargeted",
        joints=joints,
        parents=local,
        positions=arrays["joints"].astype(np.float64)[:, joints],
        rotations=arrays["rotations"].astype(np.float64)[:, joints],
        rest_positions=arrays["rest_joints"].astype(np.float64)[joints],
        rest_rotations=arrays["rest_rotations"].astype(np.float64)[joints],
        frame_rate=rate,
        vertices=arrays["rest_vertices"].astype(np.float64),
        faces=arrays["faces"].astype(np.int64),
        weights=weights[:, joints],
    )
    return rig, up


def _phase1(run: Path, options: Options) -> tuple[Rig, int]:
    from nmjax import run_folder

    skeleton = run_folder.read_skeleton(run)
    kept = run_folder.pruned_skeleton(run)
    keep = np.ones(skeleton.num_keypoints, bool) if kept is None else kept[1]
    keypoints = _pick(run_folder.load_trajectories(run, options.split), options, run)
    rate, up = run_folder.motion_format(run)
    refined = (
        None if options.unrefined else run_folder.read_refined(run, options.split, options.seq)
    )
    if refined is not None:
        if len(refined["positions"]) != len(keypoints):
            raise ValueError(
                f"{run_folder.refined_file(run, options.split, options.seq)} has "
                f"{len(refined['positions'])} frames, the keypoints {len(keypoints)}; refine it "
                f"again with `nmjax refine --run {run} --split {options.split} --seq "
                f"{options.seq}` (or pass --unrefined)"
            )
        return refined_rig(refined, options.seq, rate), up
    rig = positions_rig(options.seq, keypoints, np.asarray(skeleton.parents), keep, rate)
    return rig, up


def refined_rig(arrays: dict[str, np.ndarray], name: str, frame_rate: float) -> Rig:
    """The rig of a refined sequence (`run_folder.read_refined`'s arrays): its joints and tree,
    the world rotations and positions of its forward kinematics, its rest pose with identity
    rotations; the animation named `<name>_refined`."""
    num = len(arrays["joints"])
    return Rig(
        name=f"{name}{REFINED_SUFFIX}",
        joints=np.asarray(arrays["joints"], np.int64),
        parents=np.asarray(arrays["parents"], np.int64),
        positions=np.asarray(arrays["positions"], np.float64),
        rotations=np.asarray(arrays["rotations"], np.float64),
        rest_positions=np.asarray(arrays["rest_positions"], np.float64),
        rest_rotations=np.broadcast_to(np.eye(3), (num, 3, 3)).copy(),
        frame_rate=frame_rate,
    )


def _phase2(run: Path, options: Options) -> tuple[Rig, int]:
    """The model's best-of-S posterior reconstruction of one whole sequence (its exported
    keypoints), placed by forward kinematics with the model's own rotations."""
    import jax
    import jax.numpy as jnp
    from flax import nnx

    from nmjax import geometry, run_folder, tasks
    from nmjax.models.dynamics import bone_lengths
    from nmjax.train import trained

    model, _, skel_run = trained.load_phase2(run)
    x = _pick(run_folder.load_trajectories(skel_run, options.split), options, skel_run)[None]
    local, recon = tasks.infer_rotations_jit(
        *nnx.split(model), jnp.asarray(x), jax.random.key(options.seed)
    )
    kept = run_folder.pruned_skeleton(skel_run)
    keep = np.ones(model.num_keypoints, bool) if kept is None else kept[1]
    rate, up = run_folder.motion_format(skel_run)
    parents = np.asarray(model.parents)
    if model.kind != "nm":  # the positional baseline outputs keypoints, no rotations
        return positions_rig(options.seq, np.asarray(recon[0]), parents, keep, rate), up
    root = model.order[0]
    positions, rotations = geometry.forward_kinematics_with_rotations(
        recon[0, :, root, :3],
        local[0],
        model.offsets(bone_lengths(jnp.asarray(x), model.parents))[0],
        model.parents,
        model.order,
    )
    joints, local_parents = kept_tree(parents, np.asarray(model.order), keep)
    positions = np.asarray(positions, np.float64)[:, joints]
    rotations = np.asarray(rotations, np.float64)[:, joints]
    rig = Rig(
        name=options.seq,
        joints=joints,
        parents=local_parents,
        positions=positions,
        rotations=rotations,
        rest_positions=positions[0],
        rest_rotations=rotations[0],
        frame_rate=rate,
    )
    return rig, up
