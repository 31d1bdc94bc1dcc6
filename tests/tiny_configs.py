"""The smallest phase-1 setting the training tests run: a two-sequence synth-arm set and the `tiny`
preset made smaller still (G=8, C=4, K=4, T=3).

One definition for the trainer, resume, sharding and pinned-loss tests: the pinned losses
(`test_pinned_losses.py`) are recorded on exactly this configuration.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from nmjax.config import SkelTrainConfig, skel_preset


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
    return dataclasses.replace(
        cfg,
        data=dataclasses.replace(cfg.data, root=str(root), grid=8, frames=3, batch_size=batch_size),
        model=dataclasses.replace(
            cfg.model, grid=8, channels=4, num_keypoints=4, hourglass_channels=(4, 4, 4)
        ),
        **changes,
    )
