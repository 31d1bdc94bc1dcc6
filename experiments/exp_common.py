"""Shared pieces of the paper-table experiments (thin: training and metrics live in nmjax).

Phase-2 runs ("nm" and the positional "vrnn") train on a phase-1 run of `paper_phase1.py` into
`runs/exp/dyn-<data>-<model>`. Every results file the scripts write carries the stamp of
`nmjax.provenance` (commit, machine, metric definitions), taken when the script starts.
"""

from __future__ import annotations

import dataclasses
import json
import shlex
import sys
import time
from pathlib import Path

from nmjax import atomic, run_folder, runs
from nmjax.config import DynTrainConfig, SkelTrainConfig, dyn_preset, replace_fields
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


def _done(run: Path, steps: int) -> bool:
    info = run / "experiment.json"
    return info.is_file() and json.loads(info.read_text()).get("steps") == steps


def dyn_run(data: str, model: str, skel: Path, steps: int) -> Path:
    """A trained phase-2 run ("nm" or "vrnn") on the phase-1 run `skel`."""
    run = RUNS / f"dyn-{data}-{model}"
    if not _done(run, steps):
        cfg = dyn_preset(data, "cpu")
        cfg = replace_fields(
            cfg,
            skel_run=str(skel),
            run=str(run),
            steps=steps,
            val_every=steps,
            ckpt_every=steps,
            model=dataclasses.replace(cfg.model, model=model),
        )
        if run.exists():
            import shutil

            shutil.rmtree(run)
        tic = time.perf_counter()
        runs.train_dynamics(cfg, progress=False)
        atomic.write_json(
            run / "experiment.json", {"steps": steps, "seconds": time.perf_counter() - tic}
        )
    return run


def training_note(runs: dict[str, Path]) -> str:
    """Markdown lines saying how far each run was trained."""
    lines = []
    for label, run in runs.items():
        cfg = json.loads((run / run_folder.CONFIG_FILE).read_text())
        info_file = run / "experiment.json"  # a phase-2 run's; a phase-1 row's run has none
        kind = SkelTrainConfig if run_folder.run_kind(run) == "skel" else DynTrainConfig
        steps = run_folder.load_config(run, kind).loop.steps  # either config.json layout
        info = json.loads(info_file.read_text()) if info_file.is_file() else {"steps": steps}
        size = ""
        if "data" in cfg and isinstance(cfg["data"], dict):
            size = (
                f", G={cfg['data']['grid']}, C={cfg['model']['channels']}, "
                f"K={cfg['model']['num_keypoints']}, batch {cfg['data']['batch_size']} x "
                f"T={cfg['data']['frames']}"
            )
        took = f"{info['seconds'] / 60:.1f} min" if "seconds" in info else "time in phase1_rows"
        lines.append(f"- {label}: `{run}` trained {info['steps']} steps ({took} on 2 cores{size})")
    return "\n".join(lines)


def training_header(runs: dict[str, Path]) -> str:
    """Markdown saying which command made a results file and how far its runs were trained."""
    return f"Command: `{command_line()}`\n\nTraining:\n{training_note(runs)}\n"
