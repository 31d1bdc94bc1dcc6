"""Untrained tiny phase-1 and phase-2 run folders (contract C10) for the task and evaluation tests.

Nothing is trained: the commands under test only need restorable checkpoints, a skeleton and the
exported test keypoints, and building them this way costs no training-step compilation.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

PARENTS = (0, 0, 1, 2, 1, 4)  # root 0; chains 0-1-2-3 and 1-4-5
ORDER = (0, 1, 2, 4, 3, 5)


def make_runs(root: Path) -> dict[str, Path]:
    """{"data", "skel", "nm", "vrnn"} folders under `root`: a 3-sequence synth-arm set (12 frames
    each), a tiny phase-1 run (G=16, K=6) and its "nm" and "vrnn" phase-2 runs."""
    from flax import nnx

    from nmjax import runs
    from nmjax.config import dyn_preset, skel_preset
    from nmjax.data import synthetic
    from nmjax.skeleton import skeleton_from_parents
    from nmjax.train import common, dyn, skel

    data = synthetic.generate(
        "synth-arm", root / "data", num_sequences=3, frames=12, points=1500, progress=False
    )
    cfg = skel_preset("synth-arm", "tiny")
    cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, root=str(data)))
    assert cfg.model.num_keypoints == len(PARENTS)
    skel_run = common.prepare_run_dir(root / "skel-synth-arm-tiny", resume=False, config=cfg)
    graphdef, state = skel.build(cfg)
    detector = nnx.merge(graphdef, state["model"])
    spread_convolutions(detector)
    state["model"] = nnx.state(detector)
    ckpt = common.Checkpointer(skel_run / "checkpoints", 1, best_metric=skel.BEST_METRIC)
    ckpt.save(1, state, metrics={skel.BEST_METRIC: 1.0})
    ckpt.close()
    skeleton = skeleton_from_parents(np.array(PARENTS))
    skeleton.save(  # every keypoint bright enough to be kept, as extract_run_skeleton records it
        skel_run / "skeleton.json",
        intensities=np.full(len(PARENTS), 0.5),
        pruned_parents=list(PARENTS),
        keep=[True] * len(PARENTS),
    )
    runs.export_keypoints(skel_run, "test")
    runs = {"data": data, "skel": skel_run}
    for kind in ("nm", "vrnn"):
        dcfg = dyn_preset("synth-arm", "tiny")
        dcfg = dataclasses.replace(
            dcfg,
            skel_run=str(skel_run),
            model=dataclasses.replace(dcfg.model, model=kind),
            run=str(root / f"dyn-{kind}"),
        )
        run = common.prepare_run_dir(root / f"dyn-{kind}", resume=False, config=dcfg)
        _, dstate = dyn.build(dcfg, skeleton.parents, skeleton.order)
        with common.Checkpointer(run / "checkpoints", 1) as c:
            c.save(1, dstate)
        runs[kind] = run
    return runs


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
