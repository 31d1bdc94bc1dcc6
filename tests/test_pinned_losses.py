"""Pins the per-step training losses of a fixed-seed tiny run of each phase.

Both were recorded when the networks and recipes became the released ones (the detector's layers
and initialisation; the dynamics model's LeakyReLU, GRU cell, initialisation, lower median and
averaged KL; lr 4e-4, no clipping, Adam restarted every epoch: here every step in phase 1, whose
tiny set has one training sequence). Phase 2's were recorded again when its GRU kept PyTorch's
two bias vectors and its rotation decoder started at the release's random rotations (no identity
shift), which changed both the initial draw and the first outputs. A change of the train step,
the loop or the data order
that alters what a run computes moves them. The tolerance leaves room for float rounding of a
reformulated convolution, not for a different loss.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from tiny_configs import small_arm_data, small_skel_config
from tiny_runs import make_fake_run

from nmjax.config import dyn_preset
from nmjax.config_io import replace_fields
from nmjax.train import dyn, metric_log, skel

SKEL_LOSSES = [31.32627296447754, 35.00435256958008, 33.2287483215332, 37.119834899902344]
DYN_LOSSES = [1.5169981718063354, 1.5589879751205444, 1.4423792362213135, 1.585466742515564]
RTOL = 1e-4


def _train_losses(run) -> list[float]:
    records = metric_log.read_metrics(run)
    assert [r["step"] for r in records if "train/loss" in r] == [1, 2, 3, 4]
    return [r["train/loss"] for r in records if "train/loss" in r]


def test_phase1_losses_are_pinned(tmp_path):
    root = small_arm_data(tmp_path / "data")
    cfg = small_skel_config(root, steps=4, log_every=1, val_every=4, val_batches=1, ckpt_every=4)
    skel.train_skeleton(
        replace_fields(cfg, run=str(tmp_path / "skel")), progress=False, finalize=False
    )
    np.testing.assert_allclose(_train_losses(tmp_path / "skel"), SKEL_LOSSES, rtol=RTOL)


def test_phase2_losses_are_pinned(tmp_path):
    fake = make_fake_run(tmp_path / "phase1")
    cfg = replace_fields(
        dyn_preset("synth-arm", "tiny"),
        skel_run=str(fake),
        run=str(tmp_path / "dyn"),
        steps=4,
        log_every=1,
        val_every=4,
        ckpt_every=4,
    )
    # The fake phase-1 run has keypoints, no detector.
    cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, inputs="sequence"))
    dyn.train_dynamics(cfg, progress=False)
    np.testing.assert_allclose(_train_losses(tmp_path / "dyn"), DYN_LOSSES, rtol=RTOL)
