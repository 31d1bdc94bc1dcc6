"""How long until a skeleton is a skeleton: phase-1 quality against training time on 2 cores.

    JAX_PLATFORMS=cpu .venv/bin/python experiments/phase1_budget.py train \
        --data synth-hand --recipe preset [--seed 0] [--steps 20000]
    JAX_PLATFORMS=cpu .venv/bin/python experiments/phase1_budget.py score [--runs DIR]
    .venv/bin/python experiments/phase1_budget.py render

`train` trains (or resumes) one long run into `runs/budget/<body>-<recipe>-s<seed>`: the `cpu`
preset stretched to `--steps` (every learning-rate decay keeps its fraction of the run,
`nmjax.config.with_steps`), with every checkpoint at a multiple of `KEEP_EVERY` steps kept for
good (`loop.keep_every`), so that each can be scored later. Recipes:

- preset:  the `cpu` preset as `nmjax train-skel --preset cpu` trains it (lr 1e-3, one Adam
           state, clipping at 1.0, the body's changes,
           `PRESETS["cpu"].skel_per_data`);
- release: the release's optimiser at the same size (lr 4e-4, Adam restarted every epoch, no
           clipping, the decays at the dataset's decay epochs as fractions of the run).

A run folder that holds checkpoints of the same configuration is resumed from its latest one, so
a run that a session's end interrupts goes on where it stopped.

`score [--watch MINUTES]` scores every kept checkpoint of every run under `--runs` that has no row
yet (with --watch, again every MINUTES as the runs go on), as the trained run of that many steps
would be scored: the checkpoint's detector is written as a phase-1 run folder of its own under
`runs/budget-at/<run>/<step>` (its affinity and keypoint statistics on the validation batches, its
skeleton by Algorithm 1: `snapshot`), then evaluated on the test split
(`nmjax.evaluate.evaluate_phase1`: SC in both definitions, tracking CD, joint distance, distinct /
kept nodes, edge precision, bone recall, ...) with one frame for the pictures. Each row is written
to `experiments/results/phase1_budget.json` as soon as it is scored (commit it: run folders do not
survive a new machine), and kept by later calls while it is what they would compute (`nmjax.rows`).
The minutes of a row are its steps at the step time measured once on the quiet machine, compilation
included (`STEP_TIME`, from `results/phase1_budget_bench/`, `nmjax bench --phase skel --preset
cpu`), not the wall time of the run, which shared its cores with other work.

`park` writes the latest checkpoint of every unfinished run to
`results/phase1_budget_state/<run>.tar.gz` (commit it at a session's end): `train` on a machine
without the run folder resumes from there.

`render` writes `phase1_budget.md` (a table per run) and `phase1_budget.png` (each measure
against minutes, a line per recipe, a panel column per body) and
`phase1_budget_skeletons.png` (the skeletons at 2k / 5k / 10k / 20k steps).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import tarfile
import tempfile
import time
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
from flax import nnx

from nmjax import provenance, rows, run_folder
from nmjax.config import SkelTrainConfig, skel_preset, with_steps
from nmjax.config_io import replace_fields
from nmjax.data import pipeline
from nmjax.data.layout import dataset_spec
from nmjax.evaluate import PHASE1_METRICS, evaluate_phase1, phase1_scores, picture_frame
from nmjax.train import checkpoints, skel, trained
from nmjax.viz import draw_pruned_tree, save_figure  # importing nmjax.viz selects Agg

RESULTS = Path(__file__).parent / "results"
ROWS_FILE = RESULTS / "phase1_budget.json"
BENCH = RESULTS / "phase1_budget_bench"
RUNS = Path("runs") / "budget"
SNAPSHOTS = Path("runs") / "budget-at"
# The latest training state of each unfinished run, committed at a session's end (`park`), so
# that the next session on a new machine resumes the run instead of starting it again.
PARKED = RESULTS / "phase1_budget_state"
STEPS = 20_000
KEEP_EVERY = 1_000
PICTURE_STEPS = (2_000, 5_000, 10_000, 20_000)
MAX_CROPS = 8  # test crops per sequence, as paper_phase1.py scores its rows
RECIPES = {
    "preset": "the cpu preset, its schedule stretched to the run",
    "release": "the release's optimiser at the cpu size: lr 4e-4, Adam restarted every epoch, "
    "no clipping, the decays at the dataset's decay epochs (as fractions of the run)",
}
BODIES = ("synth-arm", "synth-hand", "synth-human", "synth-quadruped")
# The runs of the curve, in the order they are trained.
PLAN = (
    ("synth-hand", "preset", 0),
    ("synth-quadruped", "preset", 0),
    ("synth-hand", "release", 0),
    ("synth-arm", "preset", 0),
)
# The last commit that changed what a row computes (the runs' training or their scoring).
SINCE = "091a63d"
METRICS = {
    **PHASE1_METRICS,
    "minutes": "the row's steps at the quiet machine's step time (`nmjax bench --phase skel "
    "--preset cpu --data BODY`, load + compute per step), plus its compile time, / 60",
}
# What the figure plots, in panel order: (score key, label, higher is better).
MEASURES = (
    ("sc", "SC (published)", True),
    ("sc_fixed_nodes", "SC (fixed nodes)", True),
    ("joint_distance", "joint distance (cube)", False),
    ("distinct_nodes", "distinct nodes", True),
    ("skeleton_kept_nodes", "kept nodes", None),
    ("edge_precision", "edge precision", True),
    ("bone_recall", "bone recall", True),
    ("tracking_cd", "tracking CD x1e4", False),
    ("tree_edit_distance", "tree edit distance", False),
    ("cd_j2j", "CD-J2J x1e-2", False),
    ("rig_fit_cd", "rig fit error x1e4", False),
)
STORE = rows.RowStore(
    ROWS_FILE, METRICS, SINCE, key=("body", "recipe", "seed", "step"), config_class=SkelTrainConfig
)


def run_config(body: str, recipe: str, seed: int = 0, steps: int = STEPS) -> SkelTrainConfig:
    """The configuration of one long run (module docstring)."""
    cfg = skel_preset(body, "cpu")
    if recipe == "release":
        spec = dataset_spec(body)
        cfg = replace_fields(
            cfg,
            learning_rate=4e-4,
            clip_norm=0.0,
            optimizer_reset="epoch",
            epochs=spec.epochs,
            decay_epochs=spec.decay_epochs,
        )
    elif recipe != "preset":
        raise ValueError(f"unknown recipe {recipe!r}; recipes: {', '.join(RECIPES)}")
    cfg = replace_fields(with_steps(cfg, steps), keep_every=KEEP_EVERY, seed=seed)
    return dataclasses.replace(cfg, run=str(run_dir(body, recipe, seed)))


def run_dir(body: str, recipe: str, seed: int, root: Path = RUNS) -> Path:
    return root / f"{body}-{recipe}-s{seed}"


def _same_run(run: Path, cfg: SkelTrainConfig) -> bool:
    """Whether `run` holds a run of `cfg` (where it lives aside)."""
    path = run / run_folder.CONFIG_FILE
    if not path.is_file():
        return False
    saved = json.loads(path.read_text())
    return rows.comparable(saved, SkelTrainConfig) == rows.comparable(cfg)


def parked_state(run: Path) -> Path:
    return PARKED / f"{run.name}.tar.gz"


def park(runs_root: Path = RUNS) -> list[Path]:
    """Writes the latest checkpoint of every unfinished run of the plan under `runs_root` (with
    its config.json and metrics.jsonl) to `PARKED/<run>.tar.gz`, atomically, and removes the
    parked state of every finished one; returns the files written."""
    written = []
    for body, recipe, seed in PLAN:
        run = run_dir(body, recipe, seed, runs_root)
        steps = run_folder.checkpoint_steps(run)
        if not steps or not _same_run(run, run_config(body, recipe, seed)):
            continue
        target = parked_state(run)
        if steps[-1] >= STEPS:
            target.unlink(missing_ok=True)
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=target.parent, suffix=".tmp")
        os.close(fd)
        try:
            with tarfile.open(tmp, "w:gz") as tar:
                for name in (run_folder.CONFIG_FILE, run_folder.METRICS_FILE):
                    tar.add(run / name, arcname=name)
                latest = run_folder.checkpoint_dir(run) / str(steps[-1])
                tar.add(latest, arcname=f"{run_folder.CHECKPOINTS}/{steps[-1]}")
            os.replace(tmp, target)
        finally:
            Path(tmp).unlink(missing_ok=True)
        print(f"parked {run.name} at step {steps[-1]}: {target} ({target.stat().st_size >> 20} MB)")
        written.append(target)
    return written


def unpark(run: Path) -> bool:
    """Restores the run folder `run` from its parked state when it holds no checkpoint and a
    parked state exists (extracted beside it, then renamed into place); returns whether it
    did."""
    source = parked_state(run)
    if run_folder.checkpoint_steps(run) or not source.is_file():
        return False
    if run.exists() and any(run.iterdir()):
        raise SystemExit(f"{run} holds files but no checkpoint; move it away to resume {source}")
    run.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(dir=run.parent, prefix=f".{run.name}-"))
    try:
        with tarfile.open(source) as tar:
            tar.extractall(staging, filter="data")
        if run.exists():
            run.rmdir()
        staging.rename(run)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    print(f"resuming {run.name} from {source} (step {run_folder.checkpoint_steps(run)[-1]})")
    return True


def train(body: str, recipe: str, seed: int, steps: int) -> Path:
    """Trains or resumes the run (module docstring), from its parked state when its folder is
    missing; returns its folder."""
    cfg = run_config(body, recipe, seed, steps)
    run = Path(cfg.run)
    unpark(run)
    resume = _same_run(run, cfg) and bool(run_folder.checkpoint_steps(run))
    if run.exists() and not resume and any(run.iterdir()):
        raise SystemExit(
            f"{run} holds a run of another configuration or no checkpoint; move it away first"
        )
    skel.train_skeleton(cfg, resume=resume, overwrite=False, progress=True)
    return run


# --- scoring ------------------------------------------------------------------------------------


def step_time(body: str) -> dict[str, float]:
    """The quiet machine's phase-1 step of `body` at the cpu preset: {"seconds_per_step",
    "compile_s", "commit", "date"} from its `nmjax bench` file."""
    path = BENCH / f"bench_{body}.json"
    if not path.is_file():
        raise SystemExit(
            f"{path} is missing: on a quiet machine run `nmjax bench --phase skel --preset cpu "
            f"--data {body} --steps 40 --warmup 5 --out {path}` first"
        )
    bench = json.loads(path.read_text())
    row = bench["rows"][0]
    return {
        "seconds_per_step": row["load_s_per_step"] + row["compute_s_per_step"],
        "compile_s": row["compile_s"],
        "commit": bench["provenance"]["commit"],
        "date": bench["provenance"]["date"],
    }


def snapshot(run: Path, step: int, root: Path = SNAPSHOTS) -> Path:
    """Checkpoint `step` of the phase-1 run `run` as a complete phase-1 run folder of its own:
    config.json, the trained model as its only (and best) checkpoint, affinity.npy and
    keypoint_stats.npz on the run's validation batches, and skeleton.json by Algorithm 1, as
    `skel.train_skeleton` finishes a run that stopped at `step`. Kept when already complete."""
    out = root / run.name / f"{step:06d}"
    if (out / run_folder.SKELETON_FILE).is_file():
        return out
    cfg = run_folder.load_config(run, SkelTrainConfig)
    model, _ = trained.restore_detector(run, step)
    # The model restored is the trained one (the weight average already applied, when kept).
    cfg = replace_fields(cfg, ema_decay=0.0, run=str(out))
    run_folder.prepare_run_dir(out, resume=False, config=cfg, overwrite=True)
    graphdef, state = nnx.split(model)
    with checkpoints.Checkpointer.of_run(out, cfg.loop, trained.BEST_METRIC) as ckpt:
        ckpt.save(step, {"model": state}, metrics={trained.BEST_METRIC: 0.0})
    val_batches = pipeline.eval_batches(cfg.data, "test", cfg.val_batches, seed=cfg.seed)
    skel.write_artifacts(out, graphdef, {"model": state}, val_batches, cfg)
    trained.complete_phase1(out, export=False)
    return out


def score_step(run: Path, key: tuple[str, str, int], step: int, stamp) -> dict[str, Any]:
    """The row of checkpoint `step` of `run` (module docstring)."""
    body, recipe, seed = key
    tic = time.perf_counter()
    folder = snapshot(run, step)
    detector = trained.Detector.load(folder)
    results = evaluate_phase1(detector, MAX_CROPS)
    parents, keep = run_folder.pruned_skeleton(folder)
    timing = step_time(body)
    return {
        "body": body,
        "recipe": recipe,
        "seed": seed,
        "step": step,
        "minutes": (timing["compile_s"] + step * timing["seconds_per_step"]) / 60,
        "step_time": timing,
        "scores": phase1_scores(results),
        "pruned_parents": parents.tolist(),
        "keep": keep.tolist(),
        "frame": picture_frame(detector),
        "score_seconds": time.perf_counter() - tic,
        "config": json.loads((run / run_folder.CONFIG_FILE).read_text()),
        "provenance": stamp,
    }


def scored_steps(run: Path) -> list[int]:
    """The run's kept checkpoints that a row stands for: the multiples of KEEP_EVERY."""
    return [s for s in run_folder.checkpoint_steps(run) if s > 0 and s % KEEP_EVERY == 0]


def score_round(runs_root: Path, stamp) -> int:
    """Scores every kept checkpoint of the plan's runs under `runs_root` that has no row that
    `STORE` keeps, under `stamp`; returns how many rows were made."""
    made = 0
    for body, recipe, seed in PLAN:
        run = run_dir(body, recipe, seed, runs_root)
        cfg = run_config(body, recipe, seed)
        if not _same_run(run, cfg):
            continue
        for step in scored_steps(run):
            stored = STORE.read()
            if STORE.keeps(STORE.find(stored, body=body, recipe=recipe, seed=seed, step=step), cfg):
                continue
            row = score_step(run, (body, recipe, seed), step, stamp)
            STORE.write(STORE.put(stored, row), stamp)
            made += 1
            s = row["scores"]
            print(
                f"{run.name} step {step}: SC {s.get('sc', float('nan')):.3f}, joint d "
                f"{s.get('joint_distance', float('nan')):.3f}, {s.get('distinct_nodes')}/"
                f"{s.get('skeleton_kept_nodes')} distinct, fit "
                f"{s.get('rig_fit_cd', float('nan')):.1f}, CD {s['tracking_cd']:.1f} "
                f"({row['score_seconds']:.0f} s)",
                flush=True,
            )
    return made


def plan_complete(runs_root: Path) -> bool:
    """Whether every run of the plan has a row for its last step."""
    stored = STORE.read()
    return all(
        STORE.find(stored, body=b, recipe=r, seed=s, step=STEPS) is not None for b, r, s in PLAN
    )


def score(runs_root: Path, watch_minutes: float = 0.0) -> int:
    """Scores the kept checkpoints without a row (`score_round`) and renders; with
    `watch_minutes` > 0, again every that many minutes, as the runs write new checkpoints,
    until every run of the plan is scored to its last step. The checkout is checked clean and
    stamped once, at the start, so the rows this call writes do not make it refuse itself."""
    rows.refuse_dirty("phase1_budget.py score", allow_dirty=False)
    stamp = provenance.stamp(METRICS)
    made = score_round(runs_root, stamp)
    render()
    while watch_minutes > 0 and not plan_complete(runs_root):
        time.sleep(60 * watch_minutes)
        new = score_round(runs_root, stamp)
        if new:
            render()
        made += new
    return made


# --- rendering ----------------------------------------------------------------------------------


def _series(stored, body: str, recipe: str) -> list[dict[str, Any]]:
    return sorted(
        (r for r in stored if r["body"] == body and r["recipe"] == recipe), key=lambda r: r["step"]
    )


def _cell(value: Any, digits: int = 3) -> str:
    if value is None:
        return "-"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def markdown(stored: list[dict[str, Any]]) -> str:
    """A table per run: a line per scored checkpoint."""
    lines = [
        "# Phase-1 quality against training time on 2 cores",
        "",
        "Each row is a kept checkpoint of one long run (`experiments/phase1_budget.py`), scored "
        "on the test split as a run stopped there would be (its own skeleton by Algorithm 1). "
        "Minutes: the steps at the quiet machine's step time, compilation included "
        "(`phase1_budget_bench/`). One seed per body: the preset's seed spread is up to 0.13 in "
        "SC, so a difference below that between two rows is no finding.",
        "",
    ]
    for body, recipe, seed in PLAN:
        series = _series(stored, body, recipe)
        if not series:
            lines += [f"## {body}, {recipe}, seed {seed}: no checkpoint scored yet", ""]
            continue
        lines += [
            f"## {body}, {recipe} ({RECIPES[recipe]}), seed {seed}",
            "",
            "| step | minutes | SC | SC fixed | joint d | distinct / kept | edge prec. | "
            "bone recall | TED | CD-J2J | fit error | tracking CD | commit |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in series:
            s = r["scores"]
            lines.append(
                f"| {r['step']} | {r['minutes']:.0f} | {_cell(s.get('sc'))} | "
                f"{_cell(s.get('sc_fixed_nodes'))} | {_cell(s.get('joint_distance'))} | "
                f"{s.get('distinct_nodes', '-')} / {s.get('skeleton_kept_nodes', '-')} | "
                f"{_cell(s.get('edge_precision'))} | {_cell(s.get('bone_recall'))} | "
                f"{_cell(s.get('tree_edit_distance'))} | {_cell(s.get('cd_j2j'), 2)} | "
                f"{_cell(s.get('rig_fit_cd'), 1)} | {s['tracking_cd']:.1f} | "
                f"{provenance.describe_commit(r['provenance'])} |"
            )
        lines.append("")
    lines += ["## Definitions", ""]
    lines += [f"- **{k}**: {v}" for k, v in METRICS.items()]
    return "\n".join(lines) + "\n"


def figure(stored: list[dict[str, Any]], path: Path, stamp) -> None:
    """Each measure against minutes: a panel row per measure, a column per body, a line per
    recipe."""
    bodies = sorted({b for b, _, _ in PLAN})
    fig, axes = plt.subplots(
        len(MEASURES), len(bodies), figsize=(4.2 * len(bodies), 2.3 * len(MEASURES)), squeeze=False
    )
    for col, body in enumerate(bodies):
        for row, (key, label, _) in enumerate(MEASURES):
            ax = axes[row, col]
            for recipe in RECIPES:
                series = [r for r in _series(stored, body, recipe) if key in r["scores"]]
                if series:
                    ax.plot(
                        [r["minutes"] for r in series],
                        [r["scores"][key] for r in series],
                        marker=".",
                        label=recipe,
                    )
            ax.set_ylabel(label, fontsize=8)
            if row == 0:
                ax.set_title(body)
            if row == len(MEASURES) - 1:
                ax.set_xlabel("minutes on 2 cores (quiet)")
            if ax.has_data():
                ax.legend(fontsize=7)
    save_figure(fig, path, title="phase 1 against training time (cpu preset, seed 0)", dpi=80)
    provenance.stamp_png(path, stamp)


def skeletons(stored: list[dict[str, Any]], path: Path, stamp) -> None:
    """The pruned skeletons at `PICTURE_STEPS` steps: a row per run, a column per step."""
    fig = plt.figure(figsize=(2.6 * len(PICTURE_STEPS), 2.8 * len(PLAN)))
    for i, (body, recipe, _) in enumerate(PLAN):
        by_step = {r["step"]: r for r in _series(stored, body, recipe)}
        for j, step in enumerate(PICTURE_STEPS):
            ax = fig.add_subplot(
                len(PLAN), len(PICTURE_STEPS), i * len(PICTURE_STEPS) + j + 1, projection="3d"
            )
            row = by_step.get(step)
            if row is None:
                ax.set_axis_off()
                ax.set_title(f"{body} {recipe}\nstep {step}: not scored yet", fontsize=7)
                continue
            s = row["scores"]
            draw_pruned_tree(
                ax,
                np.asarray(row["frame"]["keypoints"]),
                row["pruned_parents"],
                np.asarray(row["keep"], bool),
                np.asarray(row["frame"]["points"]),
                title=f"{body} {recipe} step {step} ({row['minutes']:.0f} min)\nSC "
                f"{_cell(s.get('sc'), 2)}, joint d {_cell(s.get('joint_distance'), 2)}, "
                f"{s.get('distinct_nodes', '?')}/{s.get('skeleton_kept_nodes', '?')} distinct",
            )
    save_figure(fig, path, title="pruned skeletons along training", dpi=90)
    provenance.stamp_png(path, stamp)


def render(out: Path = RESULTS) -> None:
    """phase1_budget.md, phase1_budget.png and phase1_budget_skeletons.png from the rows."""
    stored = STORE.read()
    stamp = provenance.stamp(METRICS)
    provenance.write_markdown(out / "phase1_budget.md", markdown(stored), stamp)
    figure(stored, out / "phase1_budget.png", stamp)
    skeletons(stored, out / "phase1_budget_skeletons.png", stamp)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("train", help="train or resume one long run")
    p.add_argument("--data", required=True, choices=BODIES)
    p.add_argument("--recipe", default="preset", choices=RECIPES)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=STEPS)
    p = sub.add_parser("score", help="score every kept checkpoint without a row, then render")
    p.add_argument("--runs", type=Path, default=RUNS, help="the folder of the long runs")
    p.add_argument(
        "--watch",
        type=float,
        default=0.0,
        metavar="MINUTES",
        help="score new checkpoints every MINUTES until every run of the plan is scored",
    )
    sub.add_parser("render", help="rewrite the table and figures from the rows")
    p = sub.add_parser("park", help="save each unfinished run's latest state for the next machine")
    p.add_argument("--runs", type=Path, default=RUNS, help="the folder of the long runs")
    args = parser.parse_args(argv)
    if args.command == "train":
        print(train(args.data, args.recipe, args.seed, args.steps))
    elif args.command == "score":
        print(f"{score(args.runs, args.watch)} rows made")
    elif args.command == "park":
        park(args.runs)
    else:
        render()


if __name__ == "__main__":
    main()
