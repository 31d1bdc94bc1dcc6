"""Shared pieces of the paper-table experiments (thin: training and metrics live in nmjax).

Phase-1 variants of one synthetic dataset, trained at the `cpu` preset for `--steps` steps into
`runs/exp/skel-<data>-<variant>` (reused when already complete with that many steps):

- ours:    Eq. 23 with the dataset's weights (paper Tables 3-8);
- gt:      L_vol replaced by the MSE to ground-truth joints, K = J (Table 2, "GT");
- no_vol:  w_vol = 0 (Tables 9-10);
- no_traj: w_traj = 0 (appendix C.2).

Phase-2 runs ("nm" and the positional "vrnn") train on the `ours` phase-1 run into
`runs/exp/dyn-<data>-<model>`.

Every results file the scripts write carries the stamp of `nmjax.provenance` (commit, machine,
metric definitions), taken when the script starts.
"""

from __future__ import annotations

import dataclasses
import json
import shlex
import sys
import time
from pathlib import Path

from nmjax import atomic, provenance, runs
from nmjax.config import SkelTrainConfig, dyn_preset, skel_preset
from nmjax.data.datasets import load_sequences
from nmjax.data.synthetic import ensure_dataset
from nmjax.train import common, skel

RESULTS = Path(__file__).parent / "results"
RUNS = Path("runs") / "exp"
VARIANTS = ("ours", "gt", "no_vol", "no_traj")


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


def skel_config(data: str, variant: str, steps: int):
    """The phase-1 configuration of `variant` (see the module docstring)."""
    cfg = skel_preset(data, "cpu")
    cfg = dataclasses.replace(cfg, steps=steps, val_every=steps, ckpt_every=steps, log_every=10)
    milestones = (max(1, int(steps * 2 / 3)), max(1, int(steps * 5 / 6)))
    cfg = dataclasses.replace(cfg, lr_milestones=milestones)
    if variant == "gt":
        cfg = supervised_by_joints(cfg, data)
    elif variant == "no_vol":
        cfg = dataclasses.replace(cfg, weights=dataclasses.replace(cfg.weights, vol=0.0))
    elif variant == "no_traj":
        cfg = dataclasses.replace(cfg, weights=dataclasses.replace(cfg.weights, traj=0.0))
    elif variant != "ours":
        raise ValueError(f"unknown variant {variant!r}; valid: {VARIANTS}")
    return cfg


def _done(run: Path, steps: int) -> bool:
    info = run / "experiment.json"
    return info.is_file() and json.loads(info.read_text()).get("steps") == steps


def skel_run(data: str, variant: str, steps: int) -> Path:
    """A trained phase-1 run of `variant` (trained now unless already there)."""
    run = RUNS / f"skel-{data}-{variant}"
    if not _done(run, steps):
        cfg = skel_config(data, variant, steps)
        tic = time.perf_counter()
        summary = skel.train(cfg, run, overwrite=True, progress=False)
        runs.finish_phase1(run)
        atomic.write_json(
            run / "experiment.json",
            {"steps": steps, "seconds": time.perf_counter() - tic, "summary": summary},
        )
    return run


def dyn_run(data: str, model: str, skel: Path, steps: int) -> Path:
    """A trained phase-2 run ("nm" or "vrnn") on the phase-1 run `skel`."""
    run = RUNS / f"dyn-{data}-{model}"
    if not _done(run, steps):
        cfg = dyn_preset(data, "cpu")
        cfg = dataclasses.replace(
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
        info = json.loads((run / "experiment.json").read_text())
        cfg = json.loads((run / common.CONFIG_FILE).read_text())
        size = ""
        if "data" in cfg and isinstance(cfg["data"], dict):
            size = (
                f", G={cfg['data']['grid']}, C={cfg['model']['channels']}, "
                f"K={cfg['model']['num_keypoints']}, batch {cfg['data']['batch_size']} x "
                f"T={cfg['data']['frames']}"
            )
        lines.append(
            f"- {label}: `{run}` trained {info['steps']} steps "
            f"({info['seconds'] / 60:.1f} min on the shared 2-core CPU{size})"
        )
    return "\n".join(lines)


def training_header(runs: dict[str, Path]) -> str:
    """Markdown saying which command made a results file and how far its runs were trained."""
    return f"Command: `{command_line()}`\n\nTraining:\n{training_note(runs)}\n"


def skeleton_section(rows: dict[str, dict]) -> str:
    """Markdown section of the skeleton measures beside SC, one row per {label: the phase-1
    results of `evaluate_phase1`} ("" when no row has them: no joints or no skeleton)."""
    from nmjax.evaluate import SKELETON_TRUTH_NOTE, skeleton_truth_table

    table = skeleton_truth_table(rows, sc=True)
    if not table:
        return ""
    return "\n".join(
        ["", "## Skeleton against the ground truth", "", SKELETON_TRUTH_NOTE, "", *table, ""]
    )


def bar_plot(
    path: Path, groups: list[str], series: dict[str, list], ylabel: str, title: str, stamp: dict
):
    """Grouped bars; series values are (mean, ci or None); the PNG carries `stamp`."""
    import matplotlib.pyplot as plt
    import numpy as np

    from nmjax.viz import save_figure  # selects the Agg backend

    fig, ax = plt.subplots(figsize=(1.6 + 1.4 * len(groups), 3.4))
    width = 0.8 / max(len(series), 1)
    x = np.arange(len(groups))
    for i, (label, values) in enumerate(series.items()):
        means = [v[0] for v in values]
        errs = [0.0 if v[1] is None or not np.isfinite(v[1]) else v[1] for v in values]
        ax.bar(x + i * width, means, width, yerr=errs, capsize=3, label=label)
    ax.set_xticks(x + width * (len(series) - 1) / 2, groups)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    save_figure(fig, path)
    provenance.stamp_png(path, stamp)
