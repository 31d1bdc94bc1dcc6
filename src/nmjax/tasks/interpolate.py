"""Motion interpolation between keyframes x_ts and x_te (Sec. 5): the posterior at x_ts, then the
prior rolled over the gap for several trajectories, keeping the one that ends closest to x_te
(`interpolate_motion`), next to the non-generative baselines Lerp (joint positions,
`lerp_keypoints`) and Slerp (local rotations inferred by the model, `slerp_keypoints`). The
positional VRNN baseline is `interpolate_motion` with a `Dynamics` of kind "vrnn". On a run
folder `run_interpolate` (`nmjax interpolate`).

In every result the two keyframes are the given ones: the methods differ only in the frames
between them.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from nmjax import geometry, run_folder
from nmjax.config import DynTrainConfig
from nmjax.models.dynamics import Dynamics, bone_lengths
from nmjax.tasks import outputs
from nmjax.tasks.inputs import TaskClips, pick_inputs, source_file_clip
from nmjax.train import dyn_inputs, trained


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


@functools.partial(jax.jit, static_argnames=("graphdef", "gap", "num_trajectories"))
def interpolate_jit(graphdef, state, x_start, x_end, key, *, gap: int, num_trajectories: int):
    """`interpolate_motion` on a split model."""
    model = nnx.merge(graphdef, state)
    return interpolate_motion(model, x_start, x_end, gap, key, num_trajectories)


@functools.partial(jax.jit, static_argnames=("graphdef", "gap"))
def slerp_jit(graphdef, state, x_start, x_end, key, *, gap: int):
    """`slerp_keypoints` on a split model."""
    return slerp_keypoints(nnx.merge(graphdef, state), x_start, x_end, gap, key)


@dataclasses.dataclass
class Interpolators:
    """The compiled interpolation methods (`outputs.INTERPOLATION_METHODS`) on one phase-2 model
    (and the optional VRNN)."""

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


def interpolation_clips(cfg: DynTrainConfig, skel_run: Path, count: int, gap: int) -> TaskClips:
    """Frames 0 .. gap of the first `count` test sequences: the keyframes and the truth between.

    "sequence": cut from keypoints_test.npz. "crop": a clip of max(T, gap + 1) frames from frame
    0, normalised with its own bounding box and run through the detector as one crop (its first
    gap + 1 frames kept), as the release's interpolation takes its keyframes.
    """
    if cfg.data.inputs == "sequence":
        trajectories = run_folder.load_trajectories(skel_run, "test")
        names, truth = pick_inputs(trajectories, count, gap + 1)
        real = np.array([min(len(trajectories[n]), gap + 1) for n in names], np.int32)
        return TaskClips(names, truth, real)
    detector = dyn_inputs.phase2_detector(skel_run, cfg.data.root)
    seqs, rate = dyn_inputs.split_sequences(detector, "test"), detector.cfg.data.sample_rate
    names = sorted(seqs)[:count]
    clips = [(seqs[n], 0) for n in names]
    truth = dyn_inputs.detect_clips(detector, clips, max(cfg.data.frames, gap + 1))[:, : gap + 1]
    real = [min(-(-seqs[n].num_frames // rate), gap + 1) for n in names]
    return TaskClips(names, truth, np.array(real, np.int32))


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
    (`interpolation_clips`). Writes interpolate.npz (`outputs.write_interpolate`: {method: (I,
    gap + 1, K, 4)} and the truth) and per input a GIF and PNG strip with one panel per method
    and the truth.
    """
    from nmjax import viz  # matplotlib only where a picture is drawn

    model, cfg, skel_run = trained.load_phase2(run)
    out = Path(out) if out is not None else Path(run) / "interpolate"
    if vrnn_run is not None:
        trained.phase2_runs(Path(run), vrnn_run)  # refuses a baseline of another skeleton or input
    if source_file is not None:
        name, truth, _ = source_file_clip(skel_run, source_file, gap + 1, source_rate)
        names = [name]
    else:
        clips = interpolation_clips(cfg, skel_run, inputs, gap)
        names, truth = clips.names, clips.keypoints
    vrnn = None if vrnn_run is None else nnx.split(trained.restore_dynamics(vrnn_run))
    interp = Interpolators(nnx.split(model), vrnn, trajectories)
    methods = outputs.interpolation_methods(vrnn is not None)
    key = jax.random.key(seed)
    results = {m: interp.run(m, truth[:, 0], truth[:, -1], gap, key) for m in methods}
    outputs.write_interpolate(
        out,
        outputs.rig_arrays(skel_run, len(model.parents)),
        results,
        truth=truth,
        names=names,
        parents=model.parents,
    )
    for i, name in enumerate(names):
        motions = [truth[i]] + [results[m][i] for m in methods]
        viz.write_motion_pictures(out / name, motions, ["truth", *methods], model.parents)
    return out
