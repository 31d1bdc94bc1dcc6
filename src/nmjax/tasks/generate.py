"""Motion generation (Sec. 5): the T_cond observed frames (run through the posterior), then prior
samples to T_cond + T_gen frames, several samples per input (`generate_motion`); on a run folder
`run_generate` (`nmjax generate`).

What was observed is returned as given: a generated motion starts with its conditioning frames.
"""

from __future__ import annotations

import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from nmjax import run_folder
from nmjax.config import DynTrainConfig
from nmjax.models.dynamics import Dynamics
from nmjax.tasks import outputs
from nmjax.tasks.inputs import TaskClips, pick_inputs, source_file_clip
from nmjax.train import dyn_inputs, trained


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


@functools.partial(jax.jit, static_argnames=("graphdef", "num_frames", "num_samples"))
def generate_jit(graphdef, state, x_cond, key, *, num_frames: int, num_samples: int):
    """`generate_motion` on a split model (nnx.split)."""
    return generate_motion(nnx.merge(graphdef, state), x_cond, num_frames, key, num_samples)


def generation_clips(
    cfg: DynTrainConfig, skel_run: Path, count: int, cond: int, gen: int, voxels: bool = False
) -> TaskClips:
    """Frames 0 .. cond + gen - 1 of the first `count` test sequences, conditioned as trained.

    "sequence": cut from keypoints_test.npz. "crop" (the release's generation): the clip is
    normalised with the bounding box of its first crop (max(T, cond) frames, T = `cfg.data.frames`)
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
    frames = cfg.data.frames
    if cfg.data.inputs == "sequence":
        trajectories = run_folder.load_trajectories(skel_run, "test")
        names, observed = pick_inputs(trajectories, count, total)
        real = np.array([min(len(trajectories[n]), total) for n in names], np.int32)
        first = None
        if voxels:
            detector = trained.Detector.load(skel_run).reading(cfg.data.root)
            seqs, data = dyn_inputs.split_sequences(detector, "test"), detector.cfg.data
            first = np.stack(
                [trained.sequence_voxels(seqs[n], data.sample_rate, data.grid)[0] for n in names]
            )
        return TaskClips(names, observed, real, first)
    detector = dyn_inputs.phase2_detector(skel_run, cfg.data.root)
    seqs, data = dyn_inputs.split_sequences(detector, "test"), detector.cfg.data
    names = sorted(seqs)[:count]
    box = max(frames, cond)
    real = np.array([min(-(-seqs[n].num_frames // data.sample_rate), total) for n in names])
    observed, first = [], []
    for name, frames in zip(names, real, strict=True):
        vox = dyn_inputs.clip_voxels(seqs[name], 0, max(total, box), data, box_frames=box)[:total]
        x_cond = detector.keypoints(vox[None, :cond])[0]
        rest = detector.keypoints(trained.sequence_windows(vox, frames))
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
    the model's best-of-S posterior samples. Writes generate.npz (`outputs.write_generate`:
    the samples, each starting with the T_cond observed frames, and the observed frames with the
    true continuation), optionally voxels.npz (decoded occupancy of every sample, uint8), and per
    input a GIF and PNG strip (observed next to the samples).
    """
    from nmjax import viz  # matplotlib only where a picture is drawn

    model, cfg, skel_run = trained.load_phase2(run)
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
    occupancy = None
    if voxels:
        detector = trained.Detector.load(skel_run)
        decoded = [detector.decode(keypoints[:, s], clips.first_voxels) for s in range(samples)]
        occupancy = np.stack(decoded, 1) >= 0.5
    outputs.write_generate(
        out,
        outputs.rig_arrays(skel_run, len(model.parents)),
        keypoints=keypoints,
        observed=observed,
        observed_frames=real_frames,
        names=names,
        parents=model.parents,
        cond=cond,
        voxels=occupancy,
    )
    for i, name in enumerate(names):
        motions = [observed[i]] + [keypoints[i, s] for s in range(samples)]
        held = real_frames[i] < cond + gen  # the sequence ends before the horizon
        labels = [f"observed (held from {real_frames[i]})" if held else "observed"]
        labels += [f"sample {s}" for s in range(samples)]
        viz.write_motion_pictures(out / name, motions, labels, model.parents)
    return out
