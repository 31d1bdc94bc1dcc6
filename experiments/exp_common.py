"""Shared pieces of the paper-table experiments (thin: training and metrics live in nmjax).

Every results file the scripts write carries the stamp of `nmjax.provenance` (commit, machine,
metric definitions), taken when the script starts.
"""

from __future__ import annotations

import dataclasses
import shlex
import sys
from pathlib import Path

from nmjax.config import SkelTrainConfig
from nmjax.data.datasets import load_sequences
from nmjax.data.synthetic import ensure_dataset

RESULTS = Path(__file__).parent / "results"
RUNS = Path("runs") / "exp"


def command_line() -> str:
    """The command that ran this script, for the results files."""
    return "JAX_PLATFORMS=cpu .venv/bin/python " + shlex.join(sys.argv)


def supervised_by_joints(cfg: SkelTrainConfig, data: str) -> SkelTrainConfig:
    """`cfg` made Table 2's ground-truth-supervised baseline: K = J keypoints, L_vol replaced by
    the MSE between keypoint k and joint k (`weights.vol_target = "joints"`), J read from the
    first training sequence of `data` in `cfg.data.root`."""
    seq = load_sequences(data, "train", ensure_dataset(data, cfg.data.root))[0]
    if seq.joints is None:
        raise ValueError(f"{data} has no ground-truth joints; the supervised variant needs them")
    return dataclasses.replace(
        cfg,
        model=dataclasses.replace(cfg.model, num_keypoints=int(seq.joints.shape[1])),
        weights=dataclasses.replace(cfg.weights, vol_target="joints"),
    )
