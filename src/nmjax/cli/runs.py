"""`nmjax extract-skeleton` and `nmjax export-keypoints`: the phase-1 artefacts phase 2 reads.

    nmjax extract-skeleton --run RUN [--neighbors N] [--prune-threshold ALPHA] [--method M]
    nmjax export-keypoints --run RUN [--split train test] [--step N]

`train-skel` runs both at its end; these commands redo one of them (another Algorithm 1
setting, a re-export after the dataset changed).
"""

from __future__ import annotations

import time
from pathlib import Path

from nmjax.cli import parser


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
