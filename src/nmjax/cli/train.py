"""`nmjax train-skel` and `nmjax train-dyn`: the two training phases, one command-line builder.

    nmjax train-skel [--data NAME] [--root DIR] [--preset default|cpu|tiny]
                     [--steps N | --fit-minutes M] [--batch-size B] [--seed S] [--run DIR]
                     [--resume] [--overwrite] [--set model.channels=16 --set weights.vol=1.0 ...]
    nmjax train-dyn  [--data NAME] [--root DIR] [--preset default|cpu|tiny] [--steps N]
                     [--batch-size B] [--seed S] [--run DIR] [--resume] [--overwrite]
                     [--skel-run DIR] [--model nm|vrnn] [--set data.inputs=sequence ...]

Both commands share their options and their meaning (`train_parser`, `train_config`): --data,
--root, --batch-size and --set data.FIELD=V set the `data` group that both phases' configs hold
(`nmjax.config.DatasetConfig`). A new run starts from the preset plus the options. `--resume`
continues `--run` from its own config.json: `--steps`, `--root` (and the log / validation /
checkpoint cadence via --set) may change; any other option that changes the saved configuration
(`--set model...`, `--seed`, `--batch-size`, another --data) is refused before anything in the
folder is written.
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


PRESETS_HELP = {
    "skel": "default: the paper's network and the release's recipe (batch 3 of 10 frames at "
    "G=64; the dataset's epochs: aist, hanco, animals, panda 200, dfaust 2000, an epoch "
    "ceil(sequences / 3) steps; Adam at 4e-4 restarted every epoch, no clipping, 0.25x and 0.1x "
    "at the dataset's decay epochs; a capture 20,000 steps, one Adam state, decays at 30%% and "
    "70%%); cpu: G=32, C=16, batch 2 of 6 frames, 2,200 steps at lr 1e-3, one Adam state, "
    "clipping at 1.0, decays at steps 1,400 and 1,900 (what measured better on 2 cores), on "
    "synth-hand also w_vol 10 and keypoints from heatmap^2; tiny: for tests. Ignored with "
    "--resume",
    "dyn": "default: the release's recipe (batch 16 of 20 frames, D_z 128, D_h 512, 150 epochs, "
    "Adam at 4e-4 restarted every epoch, KL weight 0.003); cpu: D_z 32, D_h 128, 3,000 steps; "
    "tiny: for tests. Ignored with --resume",
}


PHASES = {"skel": "phase-1", "dyn": "phase-2"}
COMMANDS = {"skel": "train-skel", "dyn": "train-dyn"}
DESCRIPTIONS = {
    "skel": "Phase 1: train the keypoint detector and affinity (paper Eq. 23).",
    "dyn": "Phase 2: train the VRNN dynamics on a phase-1 run.",
}
DATA_HELP = {
    "skel": "one of {names} (default: the one --root's meta.json names, a capture prepared with "
    "`nmjax prepare-data --from RAW --root DIR`; without --root synth-hand)",
    "dyn": "one of {names}, the dataset of the phase-1 run (default synth-hand)",
}
ROOT_HELP = {
    "skel": "dataset folder (default data/DATA); its meta.json's up axis and frame rate are the "
    "run's",
    "dyn": "dataset folder the 'crop' inputs read the sequences from (default: the phase-1 run's)",
}


def _config_class(phase: str) -> type:
    from nmjax.config import DynTrainConfig, SkelTrainConfig

    return {"skel": SkelTrainConfig, "dyn": DynTrainConfig}[phase]


def train_parser(phase: str) -> Parser:
    """The parser of `nmjax train-skel` ("skel") or `nmjax train-dyn` ("dyn"): the options both
    trainers share, then the phase's own (phase 1: --fit-minutes; phase 2: --skel-run,
    --model)."""
    from nmjax.config import DATASETS, PRESETS
    from nmjax.config_io import add_override_argument

    p = parser(COMMANDS[phase], DESCRIPTIONS[phase])
    p.add_argument("--data", default=None, help=DATA_HELP[phase].format(names=", ".join(DATASETS)))
    p.add_argument("--root", default=None, help=ROOT_HELP[phase])
    p.add_argument("--preset", default="default", choices=PRESETS, help=PRESETS_HELP[phase])
    p.add_argument(
        "--steps",
        type=int,
        default=None,
        help="total optimizer steps, instead of the preset's epochs (the learning-rate decays "
        "keep their fractions of the run); with --resume, where the run ends",
    )
    p.add_argument(
        "--batch-size",
        type=int,
        default=None,
        help="global batch, data.batch_size (a multiple of the devices)",
    )
    p.add_argument("--seed", type=int, default=None, help="the run's seed (default the preset's)")
    p.add_argument("--run", default=None, help=f"run folder (default runs/{phase}-DATA-STAMP)")
    p.add_argument("--resume", action="store_true", help="continue --run from its checkpoint")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --run")
    p.add_argument(
        "--init-from",
        default=None,
        metavar="RUN",
        help=f"start a new run from the trained weights of RUN (a {PHASES[phase]} run, e.g. one "
        "`nmjax import-release` wrote) with a fresh optimizer; its network must be RUN's",
    )
    add_override_argument(
        p, "override a config field, e.g. --set model.channels=16 --set data.batch_size=4"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    if phase == "skel":
        p.add_argument(
            "--fit-minutes",
            type=float,
            default=None,
            metavar="M",
            help="time the train step first, then train as many steps as fit M minutes of wall "
            "time, the learning-rate milestones at the preset's fractions of the run",
        )
    else:
        from nmjax.models.dynamics import MODELS

        p.add_argument("--skel-run", default=None, help="phase-1 run (default: latest of DATA)")
        p.add_argument("--model", default=None, choices=MODELS, help="nm (FK, default) or vrnn")
    _distributed_args(p)
    return p


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
    if args.data is not None and args.data != cfg.data.name:
        raise ValueError(
            f"--resume continues {args.run}, a run of {cfg.data.name!r}; drop --data "
            f"{args.data} or start a new run"
        )
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


def _preset_config(args: argparse.Namespace, phase: str):
    """A new run's preset.

    Phase 1 takes its dataset from --data, else from the meta.json of --root (a prepared capture
    names the `capture` spec), else synth-hand, and the up axis and frame rate that the set's
    meta.json records (`nmjax.data.layout.training_config`); phase 2 from --data, else
    synth-hand.
    """
    from nmjax.config import dyn_preset

    if phase == "dyn":
        return dyn_preset(args.data or "synth-hand", args.preset)
    from nmjax.data.layout import training_config

    name = args.data or (None if args.root is not None else "synth-hand")
    return training_config(name, args.root, args.preset)


def train_config(args: argparse.Namespace, phase: str):
    """The preset (or, with --resume, the run's saved config) plus the command-line options, for
    either phase, checked as its trainer checks it (`check_config`); on a resume the trainer
    refuses what changes the run.

    The options are applied in one order for both phases: --root, the phase's own (--skel-run,
    --model), --batch-size, --seed, --set, --steps (a new run counts in steps instead of epochs,
    the decays at their fractions, `with_steps`; a resumed one keeps its schedule and only moves
    its end), --run and --init-from.
    """
    from nmjax.config import with_steps
    from nmjax.config_io import apply_overrides, replace_fields, replace_paths

    if args.resume:
        cfg = _saved_config(args, _config_class(phase))
    else:
        cfg = _preset_config(args, phase)
    options = {
        "data.root": args.root,
        "skel_run": getattr(args, "skel_run", None),
        "model.model": getattr(args, "model", None),
        "data.batch_size": args.batch_size,
        "seed": args.seed,
    }
    cfg = replace_paths(cfg, {k: v for k, v in options.items() if v is not None})
    cfg = apply_overrides(cfg, args.overrides)
    if args.steps is not None:
        resized = replace_fields(cfg, steps=args.steps)
        cfg = resized if args.resume else with_steps(cfg, args.steps)
    if args.run is not None:
        cfg = dataclasses.replace(cfg, run=str(args.run))
    cfg = _init_from(cfg, args)
    from nmjax.train import dyn, skel

    {"skel": skel.check_config, "dyn": dyn.check_config}[phase](cfg)
    return cfg


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
    p = train_parser("skel")
    args = p.parse_args(argv)
    positive(p, args, "steps", "batch_size")
    if args.fit_minutes is not None:  # refused here, before a run's config is read
        if not args.fit_minutes > 0:
            p.error(f"--fit-minutes must be > 0, got {args.fit_minutes}")
        if args.resume:
            p.error("--fit-minutes sets a new run's schedule; --resume keeps the run's own")
        if args.steps is not None:
            p.error("give --steps or --fit-minutes, not both")
    _initialize(args)
    from nmjax.train import skel

    cfg = train_config(args, "skel")
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


def train_dyn(argv: list[str]) -> int:
    p = train_parser("dyn")
    args = p.parse_args(argv)
    positive(p, args, "steps", "batch_size")
    _initialize(args)
    from nmjax.train import dyn

    summary = dyn.train_dynamics(
        train_config(args, "dyn"),
        resume=args.resume,
        overwrite=args.overwrite,
        progress=not args.no_progress,
    )
    last = {"step": summary.step, **summary.validation} if summary.validation else {}
    print(f"run folder: {summary.run}; final validation: {json.dumps(last)}")
    return 0
