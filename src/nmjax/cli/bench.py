"""`nmjax bench`: steps/s, load vs compute, compile time and memory of the train steps (the
measurements are `nmjax.bench`'s)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from nmjax.cli import Parser


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    from nmjax.bench import PHASES
    from nmjax.config import PRESETS
    from nmjax.config_io import add_override_argument

    parser = Parser(
        prog="nmjax bench",
        description="Steps/s, frames/s, data-loading vs compute time, compile time and peak "
        "memory of the phase-1 and phase-2 train steps.",
    )
    parser.add_argument("--phase", nargs="+", default=list(PHASES), choices=PHASES)
    parser.add_argument("--preset", nargs="+", default=["cpu", "default"], choices=PRESETS)
    parser.add_argument("--data", default="synth-arm", help="dataset of the phase-1 pipeline")
    parser.add_argument("--steps", type=int, default=10, help="timed steps per row")
    parser.add_argument("--warmup", type=int, default=2, help="untimed steps after compiling")
    add_override_argument(
        parser,
        "config override for both phases, or one phase with a prefix: "
        "skel:model.channels=16, dyn:data.batch_size=8",
    )
    parser.add_argument(
        "--compute-dtype",
        default=None,
        choices=("float32", "bfloat16"),
        help="phase-1 3D convolutions (model.compute_dtype); default: the preset's",
    )
    parser.add_argument(
        "--dyn-model", nargs="+", default=["nm"], choices=("nm", "vrnn"), help="phase-2 models"
    )
    parser.add_argument(
        "--keypoints", type=int, default=None, help="phase-2 K (default: the dataset's K)"
    )
    parser.add_argument(
        "--same-process",
        action="store_true",
        help="measure every row in this process (default: one fresh process per row, so that "
        "each row's peak memory is its own)",
    )
    parser.add_argument("--out", default=None, help="write the header and rows as JSON here")
    args = parser.parse_args(list(argv))
    if args.steps < 1 or args.warmup < 0:
        parser.error(f"--steps must be >= 1 and --warmup >= 0, got {args.steps}, {args.warmup}")
    return args


def bench(argv: list[str]) -> int:
    from nmjax import atomic
    from nmjax import bench as bench_lib

    args = parse_args(argv)
    result = bench_lib.run(args)
    if args.out is not None:
        atomic.write_json(args.out, result)
        print(f"wrote {args.out}")
    return 0
