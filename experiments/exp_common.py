"""Shared pieces of the paper-table experiments (thin: training and metrics live in nmjax).

Every results file the scripts write carries the stamp of `nmjax.provenance` (commit, machine,
metric definitions), taken when the script starts.
"""

from __future__ import annotations

import dataclasses
import json
import shlex
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from nmjax import provenance, run_folder
from nmjax.config import SkelTrainConfig
from nmjax.config_io import config_to_dict
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


def finished(
    run: Path, cfg: Any, comparable: Callable[[dict[str, Any]], dict[str, Any]]
) -> dict[str, Any] | None:
    """`run`'s config.json when the folder holds a finished run of `cfg` (the same configuration
    as `comparable` reads both, a checkpoint at its last step), else None."""
    try:
        saved = json.loads((run / run_folder.CONFIG_FILE).read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None
    steps = run_folder.checkpoint_steps(run)
    same = comparable(saved) == comparable(config_to_dict(cfg))
    return saved if same and steps and steps[-1] >= cfg.loop.steps else None


def refuse_dirty(script: str, allow_dirty: bool) -> None:
    """Stops a row-making script (`paper_phase1.py`, `paper_phase2.py`) on a checkout with
    uncommitted changes, whose rows no later run could keep, unless `allow_dirty`."""
    if provenance.stamp().get("dirty") is not False and not allow_dirty:
        raise SystemExit(
            f"{script}: the checkout has uncommitted changes (or is not a git clone), so its "
            "rows could not be kept by a later run; commit first, train from a clean worktree, "
            "or pass --allow-dirty"
        )
