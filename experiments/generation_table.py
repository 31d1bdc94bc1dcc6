"""Generation measured: diversity, bone-length error and set distance to real motion of Ours
("nm"), the positional VRNN and hold-last-pose at horizons of 25, 100 and 300 frames.

    JAX_PLATFORMS=cpu .venv/bin/python experiments/generation_table.py --data synth-arm \
        --skel-run runs/skel-synth-arm-... [--nm-run RUN] [--vrnn-run RUN2] [--dyn-steps 3000]

Trains the phase-2 "nm" and "vrnn" runs on --skel-run unless they are given (what `nmjax
train-dyn --skel-run SKEL --model M --preset cpu --steps N --run DIR` does, into
`runs/exp/gen-<data>-<model>`; a finished run of the same configuration there is reused), then
runs `nmjax evaluate --run NM --vrnn-run VRNN --generation` (written into NM/eval/) and writes
experiments/results/generation_<data>.md and generation_<data>.png, stamped with the commit,
machine and metric definitions (`nmjax.provenance`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import exp_common as ec
import phase2_tables

from nmjax import atomic, provenance, run_folder, viz
from nmjax.cli import main as nmjax_main
from nmjax.config import DynTrainConfig, dyn_preset
from nmjax.config_io import replace_fields
from nmjax.evaluate import (
    GEN_HORIZONS,
    GENERATION_METRICS,
    REFERENCE,
    evaluate_generation_run,
    generation_markdown,
)

EXPERIMENT_FILE = "experiment.json"  # {"steps", "seconds"}: written once the training finished


def dyn_config(data: str, model: str, skel: Path, steps: int, preset: str, run: Path):
    """The configuration `nmjax train-dyn --preset PRESET --steps STEPS` trains."""
    cfg = dyn_preset(data, preset)
    return replace_fields(
        cfg,
        skel_run=str(skel),
        run=str(run),
        steps=steps,
        model=dataclasses.replace(cfg.model, model=model),
    )


def phase2_run(data: str, model: str, skel: Path, steps: int, preset: str, runs: Path) -> Path:
    """A finished phase-2 run of `model` on `skel`: reused when there, trained otherwise."""
    run = runs / f"gen-{data}-{model}"
    expected = dyn_config(data, model, skel, steps, preset, run)
    info = run / EXPERIMENT_FILE
    if info.is_file() and json.loads(info.read_text()).get("steps") == steps:
        if run_folder.load_config(run, DynTrainConfig) == expected:
            return run
    if run.exists():
        raise SystemExit(
            f"{run} exists but is not a finished {model} run of {steps} steps on {skel} at the "
            f"{preset} preset; delete it, or pass it as --{model}-run to evaluate it as it is"
        )
    tic = time.perf_counter()
    argv = ["--data", data, "--skel-run", str(skel), "--model", model, "--preset", preset]
    if nmjax_main(["train-dyn", *argv, "--steps", str(steps), "--run", str(run)]) != 0:
        raise SystemExit(f"nmjax train-dyn {' '.join(argv)} failed")
    atomic.write_json(info, {"steps": steps, "seconds": time.perf_counter() - tic})
    return run


def run_note(label: str, run: Path) -> str:
    """One markdown line: the run folder, its steps and (when this script trained it) time."""
    cfg = run_folder.load_config(run, DynTrainConfig)
    size = f"D_z={cfg.model.latent}, D_h={cfg.model.hidden}, kl_weight {cfg.kl_weight}"
    info = run / EXPERIMENT_FILE
    took = ""
    if info.is_file():
        took = f", {json.loads(info.read_text())['seconds'] / 60:.1f} min on the shared CPU"
    return f"- {label}: `{run}`, {cfg.loop.steps} steps ({size}{took})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="dataset of the phase-1 run")
    parser.add_argument("--skel-run", required=True, type=Path, help="phase-1 run folder")
    parser.add_argument("--nm-run", type=Path, help="phase-2 'nm' run (default: trained)")
    parser.add_argument("--vrnn-run", type=Path, help="phase-2 'vrnn' run (default: trained)")
    parser.add_argument("--dyn-steps", type=int, default=3000, help="steps of trained runs")
    parser.add_argument("--preset", default="cpu", help="phase-2 preset of trained runs")
    parser.add_argument("--runs", type=Path, default=ec.RUNS, help="folder of trained runs")
    parser.add_argument("--horizons", type=int, nargs="+", default=list(GEN_HORIZONS))
    parser.add_argument("--samples", type=int, default=10)
    parser.add_argument("--cond", type=int, default=5)
    parser.add_argument("--clips", type=int, default=4, help="conditioning clips per sequence")
    parser.add_argument("--results", type=Path, default=ec.RESULTS, help="folder of the .md")
    args = parser.parse_args()
    stamp = provenance.stamp(GENERATION_METRICS)
    nm = args.nm_run or phase2_run(
        args.data, "nm", args.skel_run, args.dyn_steps, args.preset, args.runs
    )
    vrnn = args.vrnn_run or phase2_run(
        args.data, "vrnn", args.skel_run, args.dyn_steps, args.preset, args.runs
    )
    options = ["--horizons", ",".join(map(str, args.horizons)), "--samples", str(args.samples)]
    options += ["--cond", str(args.cond), "--clips", str(args.clips)]
    results = evaluate_generation_run(
        nm,
        vrnn_run=vrnn,
        horizons=tuple(args.horizons),
        cond=args.cond,
        samples=args.samples,
        clips=args.clips,
    )
    plot = f"generation_{args.data}.png"
    viz.plot_generation(
        args.results / plot, results, reference=REFERENCE, title=f"{args.data}: generation"
    )
    provenance.stamp_png(args.results / plot, stamp)
    _, body = generation_markdown(results).split("\n", 1)  # without its title
    text = "\n".join(
        [
            f"# Generation on {args.data}: diversity, bone-length error, set distance to real "
            "motion",
            "",
            f"Command: `{ec.command_line()}`",
            "",
            "Evaluation: `nmjax evaluate --run "
            f"{nm} --vrnn-run {vrnn} --generation {' '.join(options)}`",
            "",
            "Runs:",
            f"- phase 1: `{args.skel_run}`",
            run_note("Ours (nm)", nm),
            run_note("VRNN", vrnn),
            body,
            f"![each measure against the horizon]({plot})",
            "",
            "## What it shows",
            "",
            phase2_tables.generation_findings(results),
            "",
        ]
    )
    path = args.results / f"generation_{args.data}.md"
    provenance.write_markdown(path, text, stamp)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
