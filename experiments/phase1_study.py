"""Phase-1 study at CPU scale: one change at a time against the `cpu` preset, at a fixed
wall-clock budget, scored on the standard test split.

    JAX_PLATFORMS=cpu .venv/bin/python experiments/phase1_study.py --data synth-arm \
        --variant base --minutes 10 [--seed 0]
    .venv/bin/python experiments/phase1_study.py --report      # rewrite the table only

Each call trains one variant (`VARIANTS`) into `runs/study/<data>-<variant>-s<seed>-<budget>`
with the `cpu` preset plus the variant's overrides, stopped by `time_limit_minutes` (so every
variant gets the same wall time, whatever its step cost; the preset's learning-rate milestones
lie beyond a short budget, so every variant trains at the constant peak rate), or after `--steps`
steps when the cores are shared with other work (a wall-clock budget then measures the load, not
the variant; compare step-budget rows only among variants of equal step cost), then evaluates it
with `nmjax.evaluate.evaluate_phase1` on the test split of the body's standard set
(`data/<data>` or `$NMJAX_DATA/<data>`, 30 sequences, seed 0) even when the variant trained on
another set. The row (command, change, steps, wall minutes, SC in both definitions, tracking CD,
bone-length variation, kept nodes, the skeleton against the ground truth: joint distance,
joint coverage, edge precision, bone recall, distinct nodes; the provenance stamp of
`nmjax.provenance`, taken before the run trained: commit, machine, metric definitions) replaces
any earlier row of the same (data, variant, seed, budget) in
`experiments/results/phase1_study.json`, and `phase1_study.md` is rewritten from it.

Variants that train on a bigger synthetic set generate it first (`nmjax.data.synthetic`) with
another seed than the standard set, so no test motion is among their training sequences.
"""

from __future__ import annotations

import argparse
import dataclasses
import fcntl
import json
import os
import shlex
import sys
import time
from pathlib import Path

import exp_common
import numpy as np

from nmjax import atomic, provenance
from nmjax.config import skel_preset, with_steps
from nmjax.config_io import apply_overrides, replace_fields
from nmjax.data import synthetic
from nmjax.data.layout import dataset_root
from nmjax.evaluate import PHASE1_METRICS, SKELETON_TRUTH_COLUMNS, evaluate_phase1
from nmjax.train.trained import Detector

RESULTS = Path(__file__).parent / "results"
RUNS = Path("runs") / "study"
# The measures of a row (the evaluation's, named as the row names them, and the study's own).
METRICS = {
    "sc, sc_fixed_nodes": f"{PHASE1_METRICS['sc']}; fixed nodes: "
    f"{PHASE1_METRICS['sc_fixed_nodes']}",
    "tracking_cd": PHASE1_METRICS["tracking"],
    "bone_length_variation": PHASE1_METRICS["bone_length_variation"],
    **{k: v for k, v in PHASE1_METRICS.items() if k.startswith(("joint_", "edge_", "bone_r"))},
    "distinct_nodes": PHASE1_METRICS["distinct_nodes"],
    "val_sc_last": "the last validation SC-score the trainer logged",
    "fuse_w_st_final": "the spatio-temporal heatmap's fusion weight in the evaluated detector",
    "heat_far_mass_last": "the last validation's median share of a heatmap's mass beyond 1.5 "
    "cells of its peak",
    "wall_minutes, load_average": "wall time of training and evaluation; the 1-minute load "
    "average when the row was written",
}


@dataclasses.dataclass(frozen=True)
class Variant:
    """One change against the `cpu` preset: config overrides and/or a bigger training set."""

    change: str
    overrides: tuple[str, ...] = ()
    sequences: int | None = None  # train on a generated set of this many sequences (seed 1)


# sigma_g is in heatmap cells: at G=32 the 8^3 heatmaps make a cell twice as wide relative to the
# body as the paper's 16^3 at G=64, so "sigma_paper" halves sigma_g to keep the paper's width in
# body units (1.5 -> 0.75 on synth-arm, 1.0 -> 0.5 on synth-hand).
VARIANTS: dict[str, Variant] = {
    "base": Variant("the cpu preset"),
    "data10x": Variant("10x training sequences (300, seed 1)", sequences=300),
    "sigma_paper": Variant("sigma_g halved (the paper's width in body units)", ("sigma_half",)),
    "vol10": Variant("w_vol = 10", ("weights.vol=10.0",)),
    "lr3e-3": Variant("peak learning rate 3e-3", ("learning_rate=3e-3",)),
    "c32": Variant(
        "detector width C = 32 (hourglass 32/48/64)",
        ("model.channels=32", "model.hourglass_channels=(32,48,64)"),
    ),
    "aug": Variant(
        "training crops turned about the up axis (+-180 deg) and shrunk by up to 25%",
        ("data.rotate_degrees=180.0", "data.scale_jitter=0.25"),
    ),
    "temp0.5": Variant(
        "keypoints from heatmap^2 (model.keypoint_temperature = 0.5)",
        ("model.keypoint_temperature=0.5",),
    ),
    # Combinations of the levers that helped one at a time.
    "data10x_aug": Variant(
        "data10x + aug", ("data.rotate_degrees=180.0", "data.scale_jitter=0.25"), sequences=300
    ),
    "data10x_temp0.5": Variant(
        "data10x + temp0.5", ("model.keypoint_temperature=0.5",), sequences=300
    ),
    "data10x_vol10": Variant("data10x + vol10", ("weights.vol=10.0",), sequences=300),
    "vol10_temp0.5": Variant(
        "vol10 + temp0.5", ("weights.vol=10.0", "model.keypoint_temperature=0.5")
    ),
    # The other levers on top of vol10_temp0.5, which measured best on synth-hand.
    "vol10_temp0.5_c32": Variant(
        "vol10_temp0.5 + c32",
        (
            "weights.vol=10.0",
            "model.keypoint_temperature=0.5",
            "model.channels=32",
            "model.hourglass_channels=(32,48,64)",
        ),
    ),
    "vol10_temp0.5_sigma_paper": Variant(
        "vol10_temp0.5 + sigma_paper",
        ("weights.vol=10.0", "model.keypoint_temperature=0.5", "sigma_half"),
    ),
    # 16^3 heatmaps at G=32: the paper's heatmap resolution, and sigma_g (in cells) its width
    # in body units, for the hand's fingers that lie under a cell apart at 8^3.
    "vol10_temp0.5_stride2": Variant(
        "vol10_temp0.5 + 16^3 heatmaps (model.heatmap_stride = 2)",
        ("weights.vol=10.0", "model.keypoint_temperature=0.5", "model.heatmap_stride=2"),
    ),
    # A lower temperature, since heatmap^2 is what moved the keypoints' localisation.
    "temp0.25": Variant(
        "keypoints from heatmap^4 (model.keypoint_temperature = 0.25)",
        ("model.keypoint_temperature=0.25",),
    ),
    "vol10_temp0.25": Variant(
        "vol10 + temp0.25", ("weights.vol=10.0", "model.keypoint_temperature=0.25")
    ),
    # The supervised ceiling: how well this detector localises when it is told where the joints
    # are (L_vol replaced by the MSE between keypoint k and joint k, K = J; Table 2's "GT").
    "gt": Variant("L_vol -> MSE to the ground-truth joints, K = J (supervised)", ("gt_joints",)),
    "gt_stride2": Variant(
        "gt + 16^3 heatmaps (model.heatmap_stride = 2)", ("gt_joints", "model.heatmap_stride=2")
    ),
    # Validate and export the running average of the weights (decay 0.99: a time constant of
    # about 100 steps) instead of the last weights, which at the constant peak rate of a short
    # budget move the keypoints from step to step (the arm's validation SC rose after its first
    # learning-rate decay in the 2,200-step run).
    "ema": Variant("weights averaged over the steps (ema_decay = 0.99)", ("ema_decay=0.99",)),
    "vol10_temp0.5_ema": Variant(
        "vol10_temp0.5 + ema",
        ("weights.vol=10.0", "model.keypoint_temperature=0.5", "ema_decay=0.99"),
    ),
    "batch4x3": Variant(
        "batch 4 crops of T = 3 frames (same frames per step)",
        ("data.batch_size=4", "data.frames=3"),
    ),
    # A finer grid, the same network: 12^3 heatmaps (cells of 0.17 in the normalised cube
    # against 0.25), the lever the study pointed to (the detector's localisation at G=32). One
    # step costs about 2.7x the G=32 step, which the full-grid rewrites of the CPU step
    # (docs/performance.md, "Full-grid layers in 2x2x2 blocks") bring inside 60 minutes for the
    # arm's 2,200 steps.
    "g48": Variant("grid G = 48 (12^3 heatmaps)", ("model.grid=48", "data.grid=48")),
    "vol10_temp0.5_g48": Variant(
        "vol10_temp0.5 + g48",
        ("weights.vol=10.0", "model.keypoint_temperature=0.5", "model.grid=48", "data.grid=48"),
    ),
}


def variant_config(data: str, name: str, minutes: float, seed: int, steps: int | None = None):
    """The training configuration of variant `name` of the study on body `data`: a wall-clock
    budget of `minutes`, or exactly `steps` steps when given."""
    if name not in VARIANTS:
        raise SystemExit(f"unknown variant {name!r}; valid: {', '.join(VARIANTS)}")
    variant = VARIANTS[name]
    cfg = skel_preset(data, "cpu")
    overrides = [o for o in variant.overrides if o not in ("sigma_half", "gt_joints")]
    if "sigma_half" in variant.overrides:
        overrides.append(f"model.sigma_g={cfg.model.sigma_g / 2}")
    cfg = apply_overrides(cfg, overrides)
    if "gt_joints" in variant.overrides:
        cfg = exp_common.supervised_by_joints(cfg, data)
    # Counted in steps: 100,000 when the wall-clock limit ends the run.
    cfg = replace_fields(
        with_steps(cfg, 100_000 if steps is None else steps),
        seed=seed,
        time_limit_minutes=minutes if steps is None else 0.0,
        data=dataclasses.replace(cfg.data, seed=seed),
    )
    if variant.sequences is not None:
        root = dataset_root(data).parent / f"{data}-n{variant.sequences}-seed1"
        synthetic.ensure_dataset(data, root, num_sequences=variant.sequences, seed=1)
        cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, root=str(root)))
    return cfg


def standard_test_detector(run: Path, data: str) -> Detector:
    """The run's detector, pointed at the standard set of `data` for its test split."""
    detector = Detector.load(run)
    cfg = detector.cfg
    return dataclasses.replace(
        detector, cfg=dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, root=None))
    )


# What SC alone hides (keypoints bunched in one place score high, a tree may link the wrong
# parts): the skeleton measures of `evaluate_phase1` (`nmjax.metrics`), copied into every row.
SKELETON_MEASURES = tuple(key for key, _ in SKELETON_TRUTH_COLUMNS) + ("skeleton_kept_nodes",)


def skeleton_measures(results: dict) -> dict[str, float | int | None]:
    """The skeleton measures of `evaluate_phase1`'s results as flat row entries (None where the
    run or its data lacks them); the joint distance's CI over sequences beside it."""
    row: dict[str, float | int | None] = {key: results.get(key) for key in SKELETON_MEASURES}
    distance = results.get("joint_distance")
    row["joint_distance"] = None if distance is None else distance["mean"]
    row["joint_distance_ci95"] = None if distance is None else distance["ci95"]
    return row


def run_extras(run: Path, detector: Detector) -> dict[str, float | None]:
    """What the run says about the heatmaps: the fusion weights of the evaluated detector
    (does the spatio-temporal branch's w_st leave its initial 0?) and the last validation
    median share of a heatmap's mass beyond 1.5 cells of its peak (logged since a15e98f)."""
    from flax import nnx

    from nmjax.train import metric_log, skel

    model = nnx.merge(detector.graphdef, detector.state)
    extras = {f"{k}_final": float(v) for k, v in skel.fusion(model).items()}
    far = [r["val/heat_far_mass"] for r in metric_log.read_metrics(run) if "val/heat_far_mass" in r]
    extras["heat_far_mass_last"] = far[-1] if far else None
    return extras


def add_run_extras(rows: list[dict]) -> list[dict]:
    """`run_extras` for the rows that lack them and whose run folder is still here."""
    for row in rows:
        run = Path(row["run"])
        if "fuse_w_st_final" not in row and (run / "config.json").is_file():
            row.update(run_extras(run, standard_test_detector(run, row["data"])))
    return rows


def run_variant(
    data: str, name: str, minutes: float, seed: int, max_crops: int, steps: int | None = None
) -> dict:
    from nmjax.train import skel

    stamp = provenance.stamp(METRICS)  # the code that trains, before the run can change it
    cfg = variant_config(data, name, minutes, seed, steps)
    budget = f"{steps} steps" if steps is not None else f"{minutes:g} min"
    run = RUNS / f"{data}-{name}-s{seed}-{budget.replace(' ', '')}"
    begin = time.perf_counter()
    summary = skel.train_skeleton(
        replace_fields(cfg, run=str(run)), overwrite=True, progress=sys.stderr.isatty()
    )
    wall = (time.perf_counter() - begin) / 60
    detector = standard_test_detector(run, data)
    results = evaluate_phase1(detector, max_crops)
    provenance.write_json(run / "study_eval.json", results, stamp)
    skeleton = json.loads((run / "skeleton.json").read_text())
    return {
        "data": data,
        "variant": name,
        "change": VARIANTS[name].change,
        "seed": seed,
        "command": "JAX_PLATFORMS=cpu .venv/bin/python " + shlex.join(sys.argv),
        "overrides": list(VARIANTS[name].overrides),
        "train_root": cfg.data.root,
        "budget": budget,
        "steps": summary.step,
        "wall_minutes": wall,
        "load_average": os.getloadavg()[0],
        "val_sc_last": summary.validation.get("val/sc_score"),
        "sc": results["sc"]["score"],
        "sc_std_over_joints": results["sc"]["std_over_joints"],
        "sc_fixed_nodes": results["sc_fixed_nodes"]["score"],
        "tracking_cd": results["tracking"]["mean"],
        "tracking_cd_ci95": results["tracking"]["ci95"],
        "bone_length_variation": results["bone_length_variation"]["mean"],
        "kept_nodes": results["bone_length_variation"]["kept_nodes"],
        **skeleton_measures(results),
        **run_extras(run, detector),
        "num_keypoints": len(skeleton["parents"]),
        "run": str(run),
        "provenance": stamp,
    }


def row_commit(row: dict) -> str:
    """The commit a row was trained at (rows before the provenance stamp record a short hash)."""
    if "provenance" in row:
        return provenance.describe_commit(row["provenance"])
    return row.get("commit") or "n/a"


def row_key(row: dict) -> tuple:
    """Rows of the same variant, seed and budget replace each other; other budgets stay."""
    return row["data"], row["variant"], row["seed"], row["budget"]


def fmt(x, digits: int = 3) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def skeleton_cells(row: dict) -> str:
    """The row's joint d, cov .05, cov .10, edge, edge 2h, bone and distinct cells; a row written
    before the skeleton measures shows its candidate-based joint d and distinct, marked *."""
    if "distinct_nodes" not in row:
        old = [f"{fmt(row['joint_distance'])}*"] + ["n/a"] * 5 + [f"{row['distinct_nearest']}*"]
        return " | ".join(old)
    distinct = row["distinct_nodes"]
    cells = [fmt(row[key]) for key in SKELETON_MEASURES[:-2]]
    return " | ".join([*cells, "n/a" if distinct is None else str(distinct)])


def write_report(rows: list[dict]) -> None:
    """phase1_study.json (every row with its own provenance) and the table phase1_study.md."""
    stamp = provenance.stamp(METRICS)
    atomic.write_json(RESULTS / "phase1_study.json", rows)
    lines = [
        "# Phase-1 study at CPU scale",
        "",
        "Made by `experiments/phase1_study.py` (the command of each row below). Every variant "
        "trains from the `cpu` preset of its commit (rows made before the detector and the "
        "training recipe became the release's, up to commit 07dc2af, trained the earlier "
        "network and recipe without the study's adopted changes) for a fixed budget (column "
        "budget: wall-clock minutes "
        "through `time_limit_minutes`, or a step count where the cores were shared) and is "
        "scored on the standard test split of its body (`nmjax.evaluate.evaluate_phase1`, up "
        "to 8 crops per test sequence). SC: Eq. 21 as published (per-frame alpha >= 0.2); SC "
        "fixed: the pruned skeleton's node set; CD: 4D-tracking Chamfer x1e4; bone var: std / "
        "mean of each bone's length over a crop, mean over bones and crops; nodes: kept / K; "
        "joint d: mean distance from a joint to its nearest kept node (the cube is [-1, 1]^3); "
        "cov: share of joint-frames with a kept node within 0.05 / 0.10; edge: share of the "
        "skeleton's edges whose nodes' joints are the same or adjacent in the true tree (2h: "
        "within two hops); bone: share of true bones whose joints' nodes are the same or "
        "adjacent in the skeleton; distinct: kept nodes that are the most frequent nearest one "
        "of some joint (bunched keypoints score a high SC with few distinct ones). Rows marked * "
        "were written before these measures (`nmjax.metrics`) existed: their joint d and "
        "distinct took every keypoint with alpha >= 0.2 in a frame as a candidate, not the "
        "skeleton's kept nodes, and the other skeleton columns are n/a. w_st: the "
        "spatio-temporal heatmap's fusion weight in the evaluated detector (initialised at 0); "
        "far mass: the last validation's median share of a heatmap's mass beyond 1.5 cells of "
        "its peak. load: the 1-minute load average when the row was written (2 cores; above 2 "
        "the run shared them).",
        "",
        "| body | variant | change | seed | budget | steps | wall min | SC | SC fixed | CD "
        "| bone var | nodes | joint d | cov .05 | cov .10 | edge | edge 2h | bone | distinct "
        "| w_st | far mass | load |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['data']} | {r['variant']} | {r['change']} | {r['seed']} | {r['budget']} | "
            f"{r['steps']} | "
            f"{r['wall_minutes']:.1f} | {fmt(r['sc'])} | {fmt(r['sc_fixed_nodes'])} | "
            f"{fmt(r['tracking_cd'], 1)} | {fmt(r['bone_length_variation'])} | "
            f"{r['kept_nodes']}/{r['num_keypoints']} | {skeleton_cells(r)} | "
            f"{fmt(r.get('fuse_w_st_final'), 2)} | "
            f"{fmt(r.get('heat_far_mass_last'), 2)} | {r['load_average']:.1f} |"
        )
    lines += ["", "## Commands", ""]
    lines += [
        f"- {r['data']} {r['variant']} s{r['seed']} ({r['budget']}, "
        f"commit {row_commit(r)}): `{r['command']}`"
        for r in rows
    ]
    provenance.write_markdown(RESULTS / "phase1_study.md", "\n".join(lines), stamp)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default="synth-arm")
    parser.add_argument("--variant", default="base", help=f"one of {', '.join(VARIANTS)}")
    parser.add_argument("--minutes", type=float, default=10.0, help="wall-clock budget")
    parser.add_argument(
        "--steps",
        type=int,
        default=None,
        help="a fixed step budget instead (for runs that share the cores with other work)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-crops", type=int, default=8, help="test crops per sequence")
    parser.add_argument("--report", action="store_true", help="only rewrite the table")
    parser.add_argument(
        "--add-extras",
        action="store_true",
        help="with --report: add the fusion weights and far mass to rows whose run is here",
    )
    args = parser.parse_args()
    row = None
    if not args.report:
        row = run_variant(
            args.data, args.variant, args.minutes, args.seed, args.max_crops, args.steps
        )
        print(json.dumps(row, indent=1))
    # Runs side by side finish at about the same time: the table is read and rewritten under a
    # lock, after the run, so that no row is lost.
    path = RESULTS / "phase1_study.json"
    with open(RESULTS / ".phase1_study.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        rows = json.loads(path.read_text()) if path.is_file() else []
        if args.add_extras:
            rows = add_run_extras(rows)
        if row is not None:
            rows = [r for r in rows if row_key(r) != row_key(row)] + [row]
        write_report(rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
