"""`nmjax prepare-data` and `nmjax synthesize`: datasets in the nmjax layout.

    nmjax prepare-data --data synth-hand [--sequences N] [--frames N] [--seed S]
    nmjax prepare-data --data dfaust --from RAW_DIR [--root DIR] [--points 20000]
    nmjax synthesize synth-arm [--root DIR] [--num-sequences N] [--frames N] [--points P]

See `nmjax.data.prepare` for the raw layout and `nmjax.data.synthetic` for the bodies.
"""

from __future__ import annotations

import time
from pathlib import Path

from nmjax.cli import parser


def prepare_data(argv: list[str]) -> int:
    from nmjax.config import DATASETS
    from nmjax.data import prepare

    p = parser(
        "prepare-data", "Write a dataset in the layout <root>/<split>/{vertices,joints}/<seq>.npy"
    )
    p.add_argument("--data", required=True, help=f"one of {', '.join(sorted(DATASETS))}")
    p.add_argument(
        "--from",
        dest="source",
        metavar="DIR",
        type=Path,
        help="real datasets: folder of raw sequences, one sub-folder of mesh frames per sequence",
    )
    p.add_argument("--root", type=Path, metavar="DIR", help="output folder (default data/<name>)")
    p.add_argument("--seed", type=int, default=0, help="sampling / generation seed")
    p.add_argument("--sequences", type=int, help="number of sequences (default: all)")
    p.add_argument("--frames", type=int, help="frames per sequence (default: all)")
    p.add_argument("--points", type=int, default=prepare.DEFAULT_POINTS, help="points per frame")
    p.add_argument(
        "--overwrite", action="store_true", help="replace a dataset already prepared at --root"
    )
    args = p.parse_args(argv)
    root = prepare.prepare_dataset(
        args.data,
        source=args.source,
        root=args.root,
        seed=args.seed,
        sequences=args.sequences,
        frames=args.frames,
        points=args.points,
        overwrite=args.overwrite,
    )
    if root is None:
        from nmjax.data.datasets import dataset_root

        where = dataset_root(args.data, args.root)
        print(f"{where} already holds a prepared {args.data!r}; pass --overwrite to replace it")
        return 0
    print(f"wrote {args.data} to {root}")
    return 0


def synthesize(argv: list[str]) -> int:
    from nmjax.data import synthetic

    p = parser("synthesize", "Generate one synthetic set and time it.")
    p.add_argument("name", choices=sorted(synthetic.BODIES))
    p.add_argument("--root", type=Path, help="output folder (default data/NAME)")
    p.add_argument("--num-sequences", type=int)
    p.add_argument("--frames", type=int)
    p.add_argument("--points", type=int, default=20000)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    args.root = args.root or Path("data") / args.name
    begin = time.perf_counter()
    root = synthetic.generate(**vars(args))  # the options are named as generate's arguments
    size = sum(f.stat().st_size for f in root.rglob("*") if f.is_file())
    print(f"wrote {root} ({size / 2**20:.0f} MiB) in {time.perf_counter() - begin:.1f} s")
    return 0
