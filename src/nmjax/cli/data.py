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
    root = prepare_dataset(
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
        from nmjax.data.layout import dataset_root

        where = dataset_root(args.data, args.root)
        print(f"{where} already holds a prepared {args.data!r}; pass --overwrite to replace it")
        return 0
    print(f"wrote {args.data} to {root}")
    return 0


def prepare_dataset(
    name: str,
    *,
    source: Path | None = None,
    root: Path | None = None,
    seed: int = 0,
    sequences: int | None = None,
    frames: int | None = None,
    points: int | None = None,
    overwrite: bool = False,
) -> Path | None:
    """Writes dataset `name` into `root` (default data/<name>): generated for a synthetic name,
    converted from the raw mesh sequences in `source` for a real one.

    The one place that picks the writer by name: `nmjax.data.prepare` converts real sets and
    `nmjax.data.synthetic` generates the others, and neither imports the other.

    Returns:
      The dataset folder, or None when `root` already holds a prepared `name` and not
      `overwrite` (nothing is changed then).

    Raises:
      ValueError: an unknown name, counts below their minimum, or `source` given for a synthetic
        set / missing for a real one.
    """
    from nmjax.config import dataset_spec
    from nmjax.data import prepare
    from nmjax.data.layout import SYNTHETIC_DATASETS, dataset_root

    dataset_spec(name)
    points = prepare.DEFAULT_POINTS if points is None else points
    for flag, value, least in (("sequences", sequences, 1), ("frames", frames, 2)):
        if value is not None and value < least:
            raise ValueError(f"--{flag} must be >= {least}, got {value}")
    if points < 1:
        raise ValueError(f"--points must be >= 1, got {points}")
    synthetic_data = name in SYNTHETIC_DATASETS
    if synthetic_data and source is not None:
        raise ValueError(f"{name} is generated; --from is only for real datasets")
    if not synthetic_data and source is None:
        raise ValueError(
            f"--data {name} needs --from DIR, the raw mesh sequences (one folder of "
            ".obj/.ply/.off frames per sequence); or use --data synth-hand"
        )
    root = dataset_root(name, root)
    if (root / "meta.json").is_file():
        if not overwrite:
            return None
        prepare.clear_dataset(root)
    if synthetic_data:
        from nmjax.data import synthetic  # lazy: only synthetic sets need the generator

        synthetic.generate(
            name, root, num_sequences=sequences, frames=frames, points=points, seed=seed
        )
    else:
        prepare.prepare_meshes(
            name,
            source,
            root,
            points=points,
            seed=seed,
            max_sequences=sequences,
            max_frames=frames,
        )
    return root


def synthesize(argv: list[str]) -> int:
    from nmjax.data import synthetic
    from nmjax.data.bodies import BODIES

    p = parser("synthesize", "Generate one synthetic set and time it.")
    p.add_argument("name", choices=sorted(BODIES))
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
