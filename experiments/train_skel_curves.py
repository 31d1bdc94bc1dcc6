"""Training curves of a phase-1 run: every loss term and the SC-score against the step.

    .venv/bin/python experiments/train_skel_curves.py --run runs/skel-synth-arm-cpu

Writes experiments/results/train_skel_<data>.json (the run's configuration, the command that made
it, wall time, the final validation metrics, the curves and, unless `--no-test`, the run's scores
on the test split under "test": SC in both definitions, tracking CD x1e4, bone-length variation
and the skeleton against the ground truth, from `nmjax.evaluate.evaluate_phase1`) and .png (one
panel per loss term, train and validation, plus the SC-score), both stamped with the commit,
machine and metric definitions (`nmjax.provenance`); `--out DIR` writes them to DIR instead.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib.pyplot as plt

from nmjax import provenance
from nmjax.evaluate import PHASE1_METRICS, evaluate_phase1, phase1_scores
from nmjax.losses import TERMS
from nmjax.train import metric_log
from nmjax.train.trained import Detector
from nmjax.viz import save_figure  # importing nmjax.viz selects the Agg backend

RESULTS = Path(__file__).parent / "results"
METRICS = {
    "train, val": "{term: [[step, value]]}: the terms of Eq. 23 (weighted as the run trained), "
    "their total and the validation SC-score, as the trainer logged them (metrics.jsonl)",
    **{f"test.{key}": text for key, text in PHASE1_METRICS.items()},
}


def curves(records: list[dict[str, float]], prefix: str) -> dict[str, list[list[float]]]:
    """{name: [[step, value], ...]} for every metric starting with `prefix`."""
    out: dict[str, list[list[float]]] = {}
    for record in records:
        for key, value in record.items():
            if key.startswith(prefix):
                out.setdefault(key[len(prefix) :], []).append([record["step"], value])
    return out


def plot(train: dict, val: dict, title: str, path: Path) -> None:
    names = [*TERMS, "loss", "sc_score"]
    fig, axes = plt.subplots(2, 5, figsize=(20, 7))
    for ax, name in zip(axes.flat, names, strict=True):
        for label, series in (("train", train), ("val", val)):
            if name in series:
                steps, values = zip(*series[name], strict=True)
                ax.plot(steps, values, label=label, marker="." if label == "val" else None)
        ax.set_title(name)
        ax.set_xlabel("step")
        if name != "sc_score":
            ax.set_yscale("log")
        if ax.has_data():
            ax.legend(fontsize=7)
    save_figure(fig, path, title=title, dpi=90)


def test_scores(run: Path, max_crops: int) -> dict[str, float]:
    """The run's headline scores on its test split (`nmjax.evaluate.phase1_scores` of
    `evaluate_phase1`: SC in both definitions, tracking CD x1e4, bone-length variation and the
    skeleton against the ground truth, each where the run and its data allow)."""
    return phase1_scores(evaluate_phase1(Detector.load(run), max_crops))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True, type=Path, help="phase-1 run folder")
    parser.add_argument("--command", default="", help="the command that trained the run")
    parser.add_argument("--wall-minutes", type=float, default=None, help="measured wall time")
    parser.add_argument("--out", type=Path, default=RESULTS, help="output folder")
    parser.add_argument("--max-crops", type=int, default=8, help="test crops per sequence")
    parser.add_argument("--no-test", action="store_true", help="skip the test-split scores")
    args = parser.parse_args(argv)
    stamp = provenance.stamp(METRICS)
    config = json.loads((args.run / "config.json").read_text())
    records = metric_log.read_metrics(args.run)
    train, val = curves(records, "train/"), curves(records, "val/")
    data = config["data"]["name"]
    final_val = {name: series[-1][1] for name, series in val.items()}
    summary = {
        "run": str(args.run),
        "command": args.command,
        "wall_minutes": args.wall_minutes,
        "steps": records[-1]["step"] if records else 0,
        "final_val": final_val,
        "config": config,
        "train": train,
        "val": val,
    }
    if not args.no_test:
        summary["test"] = test_scores(args.run, args.max_crops)
    args.out.mkdir(parents=True, exist_ok=True)
    provenance.write_json(args.out / f"train_skel_{data}.json", summary, stamp)
    figure = args.out / f"train_skel_{data}.png"
    plot(train, val, f"phase 1 on {data} ({summary['steps']} steps)", figure)
    provenance.stamp_png(figure, stamp)
    print({k: round(v, 4) for k, v in final_val.items()})
    if "test" in summary:
        print("test:", {k: round(v, 4) for k, v in summary["test"].items()})


if __name__ == "__main__":
    main()
