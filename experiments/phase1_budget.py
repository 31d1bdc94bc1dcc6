"""How long until a skeleton is a skeleton: phase-1 quality against training time on 2 cores.

    JAX_PLATFORMS=cpu .venv/bin/python experiments/phase1_budget.py train \
        --data synth-hand --recipe preset [--seed 0] [--steps 20000]

`train` trains (or resumes) one long run into `runs/budget/<body>-<recipe>-s<seed>`: the `cpu`
preset stretched to `--steps` (every learning-rate decay keeps its fraction of the run,
`nmjax.config.with_steps`), with every checkpoint at a multiple of `KEEP_EVERY` steps kept for
good (`loop.keep_every`), so that each can be scored later. Recipes:

- preset:  the `cpu` preset as `nmjax train-skel --preset cpu` trains it (lr 1e-3, one Adam
           state, clipping at 1.0, the body's `CPU_BODY_CHANGES`);
- release: the release's optimiser at the same size (lr 4e-4, Adam restarted every epoch, no
           clipping, the decays at the dataset's decay epochs as fractions of the run).

A run folder that holds checkpoints of the same configuration is resumed from its latest one, so
a run that a session's end interrupts goes on where it stopped.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from nmjax import run_folder, runs
from nmjax.config import SkelTrainConfig, skel_preset, with_steps
from nmjax.config_io import config_to_dict, replace_fields
from nmjax.data.layout import dataset_spec
from nmjax.train import skel

RUNS = Path("runs") / "budget"
STEPS = 20_000
KEEP_EVERY = 1_000
RECIPES = {
    "preset": "the cpu preset, its schedule stretched to the run",
    "release": "the release's optimiser at the cpu size: lr 4e-4, Adam restarted every epoch, "
    "no clipping, the decays at the dataset's decay epochs (as fractions of the run)",
}
BODIES = ("synth-arm", "synth-hand", "synth-human", "synth-quadruped")


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


def run_dir(body: str, recipe: str, seed: int) -> Path:
    return RUNS / f"{body}-{recipe}-s{seed}"


def _same_config(run: Path, cfg: SkelTrainConfig) -> bool:
    path = run / run_folder.CONFIG_FILE
    if not path.is_file():
        return False
    saved = json.loads(path.read_text())
    wanted = config_to_dict(cfg)
    for config in (saved, wanted):
        config["loop"].pop("steps_per_epoch", None)
    return saved == json.loads(json.dumps(wanted))


def train(body: str, recipe: str, seed: int, steps: int) -> Path:
    """Trains or resumes the run (module docstring); returns its folder."""
    cfg = run_config(body, recipe, seed, steps)
    run = Path(cfg.run)
    resume = _same_config(run, cfg) and bool(run_folder.checkpoint_steps(run))
    if run.exists() and not resume and any(run.iterdir()):
        raise SystemExit(
            f"{run} holds a run of another configuration or no checkpoint; move it away first"
        )
    skel.train_skeleton(cfg, resume=resume, overwrite=False, progress=True)
    runs.finish_phase1(run)
    return run


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("train", help="train or resume one long run")
    p.add_argument("--data", required=True, choices=BODIES)
    p.add_argument("--recipe", default="preset", choices=RECIPES)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=STEPS)
    args = parser.parse_args(argv)
    if args.command == "train":
        print(train(args.data, args.recipe, args.seed, args.steps))


if __name__ == "__main__":
    main()
