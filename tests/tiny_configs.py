"""The smallest phase-1 setting the training tests run: a two-sequence synth-arm set and the `tiny`
preset made smaller still (G=8, C=4, K=4, T=3).

One definition for the trainer, resume, sharding and pinned-loss tests: the pinned losses
(`test_pinned_losses.py`) are recorded on exactly this configuration. `short_skel_config` is the
6-step run of the trainer and resume tests, `fake_run_dyn_config` the tiny phase-2 preset on
`tiny_runs.make_fake_run`'s folder.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from nmjax.config import DynTrainConfig, SkelTrainConfig, dyn_preset, skel_preset
from nmjax.config_io import replace_fields


def small_arm_data(root: Path) -> Path:
    """Generates the synth-arm set of the tests under `root`: 2 sequences of 8 frames."""
    from nmjax.data import synthetic

    return synthetic.generate(
        "synth-arm", root, num_sequences=2, frames=8, points=2000, progress=False
    )


def small_skel_config(root: Path | str, batch_size: int = 1, **changes) -> SkelTrainConfig:
    """The `tiny` synth-arm preset at G=8, C=4, K=4, T=3, B=`batch_size`, reading `root`; the
    keyword arguments replace top-level fields (steps, log_every, ...)."""
    cfg = skel_preset("synth-arm", "tiny")
    return replace_fields(
        cfg,
        data=dataclasses.replace(cfg.data, root=str(root), grid=8, frames=3, batch_size=batch_size),
        model=dataclasses.replace(
            cfg.model, grid=8, channels=4, num_keypoints=4, hourglass_channels=(4, 4, 4)
        ),
        **changes,
    )


def short_skel_config(root: Path | str, **changes) -> SkelTrainConfig:
    """`small_skel_config` (B=1) for 6 steps, decays at 4 and 5, logging and checkpointing every
    step, validating every 3 on one batch; the keyword arguments replace top-level fields."""
    run = dict(steps=6, lr_milestones=(4, 5), log_every=1, val_every=3, val_batches=1, ckpt_every=1)
    return small_skel_config(root, **(run | changes))


def fake_run_dyn_config(skel_run: Path | str, run: Path | str, **changes) -> DynTrainConfig:
    """The tiny phase-2 preset on a fake phase-1 run (`tiny_runs.make_fake_run`), into `run`: its
    exported keypoints ("sequence" inputs), as the fake run has no detector to run on crops."""
    cfg = dyn_preset("synth-arm", "tiny")
    cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, inputs="sequence"))
    return replace_fields(cfg, skel_run=str(skel_run), run=str(run), **changes)
