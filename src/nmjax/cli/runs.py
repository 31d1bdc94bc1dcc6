"""`nmjax extract-skeleton` and `nmjax export-keypoints`, the phase-1 artefacts phase 2 reads,
and `nmjax refine`, the optional articulated refinement of a phase-1 run's skeleton.

    nmjax extract-skeleton --run RUN [--neighbors N] [--prune-threshold ALPHA] [--method M]
    nmjax export-keypoints --run RUN [--split train test] [--step N]
    nmjax refine --run RUN [--seq NAME] [--split test] [--iters N] [--fixed-weights]
                 [--no-progress]

`train-skel` runs the first two at its end; these commands redo one of them (another Algorithm 1
setting, a re-export after the dataset changed). `refine` is never run by training (the paper's
pipeline has no such step): it writes RUN/refined/<split>/<seq>.npz, which `nmjax export` and
`nmjax view` then read (`nmjax.export.refine`).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

from nmjax.cli import parser, positive


def extract_skeleton(argv: list[str]) -> int:
    from nmjax import run_folder
    from nmjax.skeleton import DEFAULT_NEIGHBORS, METHODS, PRUNE_THRESHOLD
    from nmjax.train import trained

    p = parser(
        "extract-skeleton",
        "Turn a phase-1 run's learned affinity into a kinematic tree (Algorithm 1).",
    )
    p.add_argument("--run", required=True, metavar="RUN", help="phase-1 run folder")
    p.add_argument(
        "--neighbors",
        type=int,
        default=DEFAULT_NEIGHBORS,
        metavar="N",
        help=f"maximum neighbours per keypoint (default {DEFAULT_NEIGHBORS})",
    )
    p.add_argument(
        "--prune-threshold",
        type=float,
        default=PRUNE_THRESHOLD,
        metavar="ALPHA",
        help=f"keypoints with mean intensity below it are pruned (default {PRUNE_THRESHOLD})",
    )
    p.add_argument(
        "--method",
        choices=METHODS,
        default="algorithm1",
        help="algorithm1: the paper's Algorithm 1 (default); filtered: weak links dropped first",
    )
    args = p.parse_args(argv)
    start = time.perf_counter()
    skeleton = trained.extract_run_skeleton(
        args.run, args.neighbors, args.prune_threshold, args.method
    )
    seconds = time.perf_counter() - start
    print(
        f"{Path(args.run) / run_folder.SKELETON_FILE}: K={skeleton.num_keypoints}, root "
        f"{skeleton.root}, depth {skeleton.depth}, parents {list(skeleton.parents)} "
        f"({seconds:.2f} s with figure)"
    )
    return 0


def export_keypoints(argv: list[str]) -> int:
    from nmjax import run_folder
    from nmjax.train import trained

    p = parser(
        "export-keypoints",
        "Run a phase-1 run's detector over every whole sequence of a split and write "
        "RUN/keypoints_SPLIT.npz (the trajectories phase 2 trains on).",
    )
    p.add_argument("--run", required=True, metavar="RUN", help="phase-1 run folder")
    p.add_argument("--split", nargs="+", default=list(run_folder.SPLITS), choices=run_folder.SPLITS)
    p.add_argument(
        "--step", type=int, default=None, help="checkpoint (default: the best, else the latest)"
    )
    args = p.parse_args(argv)
    if not Path(args.run).is_dir():
        raise FileNotFoundError(f"--run {args.run} does not exist; give a phase-1 run folder")
    detector = trained.Detector.load(args.run, args.step)
    for split in args.split:
        print(f"wrote {trained.export_keypoints(args.run, split, detector=detector)}")
    return 0


def refine(argv: list[str]) -> int:
    from nmjax import run_folder
    from nmjax.skeleton_refine import RefineSettings

    defaults = RefineSettings()
    p = parser(
        "refine",
        "Fit an articulated model (constant bone lengths, full rotations with twist, fitted skin "
        "weights) to a phase-1 run's sequences, starting from its skeleton and keypoints; "
        "writes RUN/refined/SPLIT/SEQ.npz, which `nmjax export` and `nmjax view` then use.",
    )
    p.add_argument("--run", required=True, metavar="RUN", help="phase-1 run folder")
    p.add_argument("--seq", default=None, metavar="NAME", help="one sequence (default: all)")
    p.add_argument(
        "--split", default="test", choices=run_folder.SPLITS, help="whose sequences (default test)"
    )
    p.add_argument(
        "--iters",
        type=int,
        default=defaults.iterations,
        metavar="N",
        help=f"Adam iterations per sequence (default {defaults.iterations})",
    )
    p.add_argument(
        "--fixed-weights", action="store_true", help="keep Algorithm 2's skin weights unfitted"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    positive(p, args, "iters")
    settings = dataclasses.replace(
        defaults, iterations=args.iters, fit_weights=not args.fixed_weights
    )

    def report(done) -> None:
        print(
            f"nmjax refine: {done.name}: fit error x1e4 {done.fit_before:.1f} -> "
            f"{done.fit_after:.1f}, {done.joints} joints, {done.frames} frames "
            f"({done.seconds:.1f} s); wrote {done.path}",
            flush=True,
        )

    from nmjax.export.refine import refine_run

    refine_run(
        args.run,
        seq=args.seq,
        split=args.split,
        settings=settings,
        progress=not args.no_progress,
        report=report,
    )
    return 0
