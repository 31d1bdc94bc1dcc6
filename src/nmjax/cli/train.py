"""`nmjax train-skel` and `nmjax train-dyn`: the two training phases.

    nmjax train-skel --data synth-arm --preset cpu [--steps N | --fit-minutes M] [--run DIR]
                     [--resume] [--overwrite] [--set model.channels=16 --set weights.vol=1.0 ...]
    nmjax train-dyn [--data NAME] [--skel-run DIR] [--model nm|vrnn] [--preset default|cpu|tiny]
                    [--steps N] [--run DIR] [--resume] [--seed S] [--batch-size B] [--set ...]

A new run starts from the preset plus the options. `--resume` continues `--run` from its own
config.json: `--steps` (and the log / validation / checkpoint cadence via --set) may change;
any other option that changes the saved configuration (`--set model...`, `--seed`,
`--batch-size`, another --data) is refused before anything in the folder is written.
`--init-from RUN` starts a new run (its own folder, a fresh optimizer) from the trained weights of
RUN, a run of the same phase (e.g. the authors' model, `nmjax import-release`): the network of
the preset and options must be RUN's (grid, K, channels, ...; a difference is refused, named),
and config.json records RUN as `init_from`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

from nmjax.cli import Parser, parser, positive


def _distributed_args(p: argparse.ArgumentParser) -> None:
    from nmjax.train.parallel import ENV_COORDINATOR, ENV_NUM_PROCESSES, ENV_PROCESS_ID

    group = p.add_argument_group(
        "several hosts", f"default: ${ENV_COORDINATOR}, ${ENV_NUM_PROCESSES}, ${ENV_PROCESS_ID}"
    )
    group.add_argument(
        "--coordinator-address", default=None, help="HOST:PORT of process 0 (multi-host runs)"
    )
    group.add_argument("--num-processes", type=int, default=None, help="number of hosts")
    group.add_argument("--process-id", type=int, default=None, help="this host, 0..N-1")


SKEL_PRESETS_HELP = (
    "default: the paper's network and the release's recipe (batch 3 of 10 frames at G=64; the "
    "dataset's epochs: aist, hanco, animals, panda 200, dfaust 2000, an epoch ceil(sequences / "
    "3) steps; Adam at 4e-4 restarted every epoch, no clipping, 0.25x and 0.1x at the "
    "dataset's decay epochs; a capture 20,000 steps, one Adam state, decays at 30%% and 70%%); "
    "cpu: G=32, C=16, batch 2 of 6 frames, 2,200 steps at lr 1e-3, one "
    "Adam state, clipping at 1.0, decays at steps 1,400 and 1,900 (what measured better on 2 "
    "cores), on synth-hand also w_vol 10 and keypoints from heatmap^2; tiny: for tests. "
    "Ignored with --resume"
)


PHASES = {"skel": "phase-1", "dyn": "phase-2"}


def _common_args(p: Parser, what: str, preset_help: str = "ignored with --resume") -> None:
    from nmjax.config import PRESETS
    from nmjax.config_io import add_override_argument

    p.add_argument("--preset", default="default", choices=PRESETS, help=preset_help)
    p.add_argument(
        "--steps",
        type=int,
        default=None,
        help="total optimizer steps, instead of the preset's epochs (the learning-rate decays "
        "keep their fractions of the run); with --resume, where the run ends",
    )
    p.add_argument("--run", default=None, help=f"run folder (default runs/{what}-DATA-STAMP)")
    p.add_argument("--resume", action="store_true", help="continue --run from its checkpoint")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --run")
    p.add_argument(
        "--init-from",
        default=None,
        metavar="RUN",
        help=f"start a new run from the trained weights of RUN (a {PHASES[what]} run, e.g. one "
        "`nmjax import-release` wrote) with a fresh optimizer; its network must be RUN's",
    )
    add_override_argument(p, "override a config field, e.g. --set model.channels=16")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    _distributed_args(p)


def _saved_config(args: argparse.Namespace, cls: type):
    """The run's own config for --resume (which needs --run)."""
    from nmjax import run_folder

    if args.run is None:
        raise ValueError("--resume needs --run DIR (the run folder to continue)")
    if args.init_from is not None:
        raise ValueError(
            "--init-from starts a new run from another run's weights and --resume continues "
            "--run itself; give one of them"
        )
    cfg = run_folder.load_config(args.run, cls)
    # A folder with nothing to resume (no checkpoint, or only imported weights) is refused here,
    # before any data is read or any detector run.
    run_folder.check_run_dir(args.run, resume=True, config=cfg)
    return cfg


def _init_from(cfg, args: argparse.Namespace):
    """`cfg` recording --init-from (as an absolute path: config.json names the source wherever
    the run is read from later)."""
    if args.init_from is None:
        return cfg
    return dataclasses.replace(cfg, init_from=str(Path(args.init_from).absolute()))


def _initialize(args: argparse.Namespace) -> None:
    from nmjax.train import parallel

    parallel.initialize_distributed(args.coordinator_address, args.num_processes, args.process_id)


# --- phase 1 ----------------------------------------------------------------------------------


def skel_config(args: argparse.Namespace):
    """The preset (or, with --resume, the run's saved config) plus the command-line options.

    A new run takes its dataset from --data, else from the meta.json of --root (a prepared
    capture names the `capture` spec), else synth-hand, and the up axis and frame rate that the
    set's meta.json records (`nmjax.data.layout.training_config`).
    """
    from nmjax.config import SkelTrainConfig, with_steps
    from nmjax.config_io import apply_overrides, replace_fields
    from nmjax.data.layout import training_config
    from nmjax.train import skel

    if args.resume:
        cfg = _saved_config(args, SkelTrainConfig)
        if args.data is not None and args.data != cfg.data.name:
            raise ValueError(
                f"--resume continues {args.run}, a run of {cfg.data.name!r}; drop --data "
                f"{args.data} or start a new run"
            )
    else:
        name = args.data or (None if args.root is not None else "synth-hand")
        cfg = training_config(name, args.root, args.preset)
    if args.root is not None:
        cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, root=args.root))
    cfg = apply_overrides(cfg, args.overrides)
    if args.steps is not None:
        # A new run counts in steps instead of epochs; a resumed one keeps its schedule and
        # only moves its end.
        resized = replace_fields(cfg, steps=args.steps)
        cfg = resized if args.resume else with_steps(cfg, args.steps)
    if args.run is not None:
        cfg = dataclasses.replace(cfg, run=str(args.run))
    cfg = _init_from(cfg, args)
    skel.check_config(cfg)
    return cfg


def skel_parser() -> Parser:
    from nmjax.config import DATASETS

    p = parser("train-skel", "Phase 1: train the keypoint detector and affinity (paper Eq. 23).")
    p.add_argument(
        "--data",
        default=None,
        help=f"one of {', '.join(DATASETS)} (default: the one --root's meta.json names, a "
        "capture prepared with `nmjax prepare-data --from RAW --root DIR`; without --root "
        "synth-hand)",
    )
    p.add_argument(
        "--root",
        default=None,
        help="dataset folder (default data/DATA); its meta.json's up axis and frame rate are the "
        "run's",
    )
    p.add_argument(
        "--fit-minutes",
        type=float,
        default=None,
        metavar="M",
        help="time the train step first, then train as many steps as fit M minutes of wall "
        "time, the learning-rate milestones at the preset's fractions of the run",
    )
    _common_args(p, "skel", SKEL_PRESETS_HELP)
    return p


def fit_to_minutes(cfg, args: argparse.Namespace, started: float):
    """--fit-minutes: times `cfg`'s step and fits the schedule (`nmjax.bench.fit_to_minutes`).

    `started` is the command's start (time.perf_counter), so the budget covers the timing too.
    """
    from nmjax import bench

    fitted, per_step = bench.fit_to_minutes(cfg, args.fit_minutes, started)
    print(
        f"--fit-minutes {args.fit_minutes:g}: {per_step:.3f} s per step -> {fitted.loop.steps} "
        f"steps, learning-rate milestones {fitted.optim.lr_milestones}, training stops by "
        f"{fitted.loop.time_limit_minutes:.1f} minutes",
        file=sys.stderr,
    )
    return fitted


def train_skel(argv: list[str]) -> int:
    started = time.perf_counter()
    p = skel_parser()
    args = p.parse_args(argv)
    positive(p, args, "steps")
    if args.fit_minutes is not None:  # refused here, before a run's config is read
        if not args.fit_minutes > 0:
            p.error(f"--fit-minutes must be > 0, got {args.fit_minutes}")
        if args.resume:
            p.error("--fit-minutes sets a new run's schedule; --resume keeps the run's own")
        if args.steps is not None:
            p.error("give --steps or --fit-minutes, not both")
    _initialize(args)
    from nmjax.train import skel

    cfg = skel_config(args)
    if args.fit_minutes is not None:
        cfg = fit_to_minutes(cfg, args, started)
    summary = skel.train_skeleton(
        cfg, resume=args.resume, overwrite=args.overwrite, progress=not args.no_progress
    )
    record = {
        "run": str(summary.run),
        "start_step": summary.start_step,
        "step": summary.step,
        "stopped_by_time_limit": summary.stop_reason == "time_limit",
        **summary.validation,
    }
    print(json.dumps(record, indent=1, default=float))
    return 0


# --- phase 2 ----------------------------------------------------------------------------------


def dyn_config(args: argparse.Namespace):
    """The preset (or, with --resume, the run's saved config) plus the command-line options."""
    from nmjax.config import DynTrainConfig, dyn_preset
    from nmjax.config_io import apply_overrides, replace_fields

    if args.resume:
        cfg = _saved_config(args, DynTrainConfig)
    else:
        cfg = dyn_preset(args.data or "synth-hand", args.preset)
        cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, model="nm"))
    # Every option given is applied; on a resume the trainer refuses what changes the run.
    if args.data is not None:
        cfg = dataclasses.replace(cfg, data=args.data)
    if args.model is not None:
        cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, model=args.model))
    if args.skel_run is not None:
        cfg = dataclasses.replace(cfg, skel_run=args.skel_run)
    for name in ("seed", "batch_size", "run"):
        if getattr(args, name) is not None:
            cfg = dataclasses.replace(cfg, **{name: getattr(args, name)})
    if args.steps is not None:  # a new run counts in steps instead of epochs
        resized = replace_fields(cfg, steps=args.steps)
        cfg = resized if args.resume else replace_fields(resized, epochs=0)
    return _init_from(apply_overrides(cfg, args.overrides), args)


def dyn_parser() -> Parser:
    from nmjax.models.dynamics import MODELS

    p = parser("train-dyn", "Phase 2: train the VRNN dynamics on a phase-1 run.")
    p.add_argument("--data", default=None, help="dataset name (default synth-hand)")
    p.add_argument("--skel-run", default=None, help="phase-1 run (default: latest of DATA)")
    p.add_argument("--model", default=None, choices=MODELS, help="nm (FK, default) or vrnn")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument(
        "--batch-size", type=int, default=None, help="global batch (a multiple of the devices)"
    )
    _common_args(p, "dyn")
    return p


def train_dyn(argv: list[str]) -> int:
    p = dyn_parser()
    args = p.parse_args(argv)
    positive(p, args, "steps", "batch_size")
    _initialize(args)
    from nmjax.train import dyn

    summary = dyn.train_dynamics(
        dyn_config(args),
        resume=args.resume,
        overwrite=args.overwrite,
        progress=not args.no_progress,
    )
    last = {"step": summary.step, **summary.validation} if summary.validation else {}
    print(f"run folder: {summary.run}; final validation: {json.dumps(last)}")
    return 0
