"""Run folders the tests build without training, all through `nmjax.run_folder`'s writers.

- `make_runs`: untrained tiny phase-1 and phase-2 runs for the task and evaluation tests (the
  commands under test only need restorable checkpoints, a skeleton and the exported test
  keypoints, and building them this way costs no training-step compilation); `make_skel_run`
  its phase-1 run alone;
- `make_fake_run`: a phase-1 run of a known 5-node tree moved by smooth rotations, with no
  detector (phase 2 trains on its keypoints, "sequence" inputs);
- `poison_after`: a trainer's step hook that makes the state NaN.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

PARENTS = (0, 0, 1, 2, 1, 4)  # root 0; chains 0-1-2-3 and 1-4-5
ORDER = (0, 1, 2, 4, 3, 5)


def make_runs(root: Path) -> dict[str, Path]:
    """{"data", "skel", "nm", "vrnn"} folders under `root`: a 3-sequence synth-arm set (12 frames
    each), a tiny phase-1 run (G=16, K=6, `make_skel_run`) and its "nm" and "vrnn" phase-2 runs."""
    from nmjax import run_folder
    from nmjax.config import dyn_preset
    from nmjax.skeleton import skeleton_from_parents
    from nmjax.train import checkpoints, dyn

    runs = make_skel_run(root)
    skel_run = runs["skel"]
    skeleton = skeleton_from_parents(np.array(PARENTS))
    for kind in ("nm", "vrnn"):
        dcfg = dyn_preset("synth-arm", "tiny")
        dcfg = dataclasses.replace(
            dcfg,
            skel_run=str(skel_run),
            model=dataclasses.replace(dcfg.model, model=kind),
            run=str(root / f"dyn-{kind}"),
        )
        run = run_folder.prepare_run_dir(root / f"dyn-{kind}", resume=False, config=dcfg)
        _, dstate = dyn.build(dcfg, skeleton.parents, skeleton.order)
        with checkpoints.Checkpointer(run_folder.checkpoint_dir(run), 1) as c:
            c.save(1, dstate)
        runs[kind] = run
    return runs


def make_skel_run(root: Path) -> dict[str, Path]:
    """{"data", "skel"} folders under `root`: a 3-sequence synth-arm set (12 frames each) and an
    untrained tiny phase-1 run on it (G=16, K=6, `PARENTS`, every node kept) with the test
    split's keypoints exported."""
    from flax import nnx

    from nmjax import run_folder
    from nmjax.config import skel_preset
    from nmjax.data import synthetic
    from nmjax.skeleton import skeleton_from_parents
    from nmjax.train import checkpoints, skel, trained

    data = synthetic.generate(
        "synth-arm", root / "data", num_sequences=3, frames=12, points=1500, progress=False
    )
    cfg = skel_preset("synth-arm", "tiny")
    cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, root=str(data)))
    assert cfg.model.num_keypoints == len(PARENTS)
    skel_run = run_folder.prepare_run_dir(root / "skel-synth-arm-tiny", resume=False, config=cfg)
    checkpoint_dir = run_folder.checkpoint_dir(skel_run)
    graphdef, state = skel.build(cfg)
    detector = nnx.merge(graphdef, state["model"])
    spread_convolutions(detector)
    state["model"] = nnx.state(detector)
    ckpt = checkpoints.Checkpointer(checkpoint_dir, 1, best_metric=skel.BEST_METRIC)
    ckpt.save(1, state, metrics={skel.BEST_METRIC: 1.0})
    ckpt.close()
    skeleton = skeleton_from_parents(np.array(PARENTS))
    run_folder.write_skeleton(  # every keypoint bright enough to be kept, as extraction records
        skel_run,
        skeleton,
        intensities=np.full(len(PARENTS), 0.5),
        pruned_parents=list(PARENTS),
        keep=[True] * len(PARENTS),
    )
    trained.export_keypoints(skel_run, "test")
    return {"data": data, "skel": skel_run}


def spread_convolutions(model) -> None:
    """Redraws every convolution kernel of the detector `model` (in place) at unit fan-in scale
    and makes its heatmap fusion sharp.

    At the released initialisation (N(0, 0.001) in the feature nets) an untrained detector puts
    every keypoint in one spot whatever its input, so bone lengths are ~0 and keypoints do not
    follow the body; a trained detector's keypoints are spread and do. Unit-scale kernels give
    such keypoints without training.
    """
    import jax.numpy as jnp
    from flax import nnx

    model.init_fan_in(nnx.Rngs(0))  # `model.init=fan_in`'s kernels
    # A sharper fusion than fan_in's (1 x frame heatmap - 4), the one these tests were built
    # with; the release's weights of 0.02 would leave every heatmap flat.
    model.fuse.kernel[...] = jnp.asarray([[2.0], [1.0]])
    model.fuse.bias[...] = jnp.asarray([-2.0])


# The fake phase-1 run's tree: root 0; chain 0 -> 1 -> 2 -> 3 and a branch 1 -> 4.
FAKE_PARENTS = (0, 0, 1, 2, 1)
FAKE_ORDER = (0, 1, 2, 3, 4)


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' formula."""
    axis = axis / np.linalg.norm(axis)
    skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * skew + (1 - np.cos(angle)) * skew @ skew


def smooth_motion(frames: int, rng: np.random.Generator, offsets: np.ndarray) -> np.ndarray:
    """(T, K, 4) keypoints of the fake tree: sinusoidal joint angles about fixed axes (Eq. 2 in
    NumPy), every alpha 0.8."""
    k = len(FAKE_PARENTS)
    axes = rng.normal(size=(k, 3))
    amp, freq, phase = rng.uniform(0.3, 1.0, k), rng.uniform(0.1, 0.3, k), rng.uniform(0, 6, k)
    out = np.zeros((frames, k, 4), np.float32)
    for t in range(frames):
        glob = np.zeros((k, 3, 3))
        for j in FAKE_ORDER:
            local = rotation_about(axes[j], amp[j] * np.sin(freq[j] * t + phase[j]))
            if FAKE_PARENTS[j] == j:
                glob[j], out[t, j, :3] = local, 0.1 * np.sin(0.05 * t)
            else:
                glob[j] = glob[FAKE_PARENTS[j]] @ local
                out[t, j, :3] = out[t, FAKE_PARENTS[j], :3] + glob[j] @ offsets[j]
    out[..., 3] = 0.8
    return out


def make_fake_run(path: Path, seed: int = 0) -> Path:
    """A phase-1 run folder at `path` holding skeleton.json (`FAKE_PARENTS`, `FAKE_ORDER`) and
    keypoints_{train,test}.npz: train sequences of 30, 25 and 4 frames, test of 16 and 12."""
    from nmjax import run_folder
    from nmjax.skeleton import skeleton_from_parents

    rng = np.random.default_rng(seed)
    offsets = rng.normal(size=(len(FAKE_PARENTS), 3))
    offsets *= rng.uniform(0.15, 0.3, (len(FAKE_PARENTS), 1)) / np.linalg.norm(
        offsets, axis=-1, keepdims=True
    )
    path.mkdir(parents=True)
    run_folder.write_skeleton(path, skeleton_from_parents(FAKE_PARENTS, FAKE_ORDER))
    for split, lengths in (("train", (30, 25, 4)), ("test", (16, 12))):
        seqs = {f"{split}{i}": smooth_motion(n, rng, offsets) for i, n in enumerate(lengths)}
        run_folder.write_trajectories(run_folder.keypoints_file(path, split), seqs)
    return path


def poison_after(poisoned_step: int):
    """A trainer's `step_hook` that makes every float of the state NaN once step
    `poisoned_step` is done. The integer step counts stay integers, so the poisoned state has the
    types of the clean one and the compiled step is reused, not compiled again."""
    import jax
    import jax.numpy as jnp

    def nan(x):
        return x * jnp.nan if jnp.issubdtype(x.dtype, jnp.floating) else x

    def hook(step, state):
        return jax.tree.map(nan, state) if step == poisoned_step else state

    return hook
