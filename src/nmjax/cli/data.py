"""`nmjax prepare-data` and `nmjax synthesize`: datasets in the nmjax layout.

    nmjax prepare-data --data synth-hand [--sequences N] [--frames N] [--seed S]
    nmjax prepare-data --data animals --from DT4D_ROOT/animals [--root DIR] [--points 20000]
    nmjax prepare-data --data dfaust --from DFAUST_ROOT [--subjects ID,...] [--overwrite]
    nmjax prepare-data --data aist --from AIST_ROOT --body-model SMPL_MALE.pkl
    nmjax synthesize synth-arm [--root DIR] [--num-sequences N] [--frames N] [--points P]

See `nmjax.data.prepare` for the raw forms and `nmjax.data.synthetic` for the bodies.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from nmjax.cli import parser


def _names_or_count(text: str) -> int | list[str]:
    """`--sequences`: a count N, or comma-separated sequence names."""
    if text.strip().isdigit():
        return int(text)
    names = [name.strip() for name in text.split(",") if name.strip()]
    if not names:
        raise argparse.ArgumentTypeError(f"expected a count or NAME[,NAME...], got {text!r}")
    return names


def _names(text: str) -> list[str]:
    names = [name.strip() for name in text.split(",") if name.strip()]
    if not names:
        raise argparse.ArgumentTypeError(f"expected ID[,ID...], got {text!r}")
    return names


def _downloads_help() -> str:
    from nmjax.data import prepare

    lines = ["real datasets as downloaded (the files, where to get them, the one command):"]
    for name, download in prepare.DOWNLOADS.items():
        model = f" --body-model {download.model}" if download.model else ""
        lines += [
            f"  {name:<16}{download.form}",
            *(f"  {'':<16}{part}" for part in download.where.splitlines()),
            f"  {'':<16}nmjax prepare-data --data {name} --from {download.source}{model}",
        ]
    lines += [
        f"  {'any real set':<16}one folder of .obj/.ply/.off frames per sequence (+ joints.npy)",
        f"  {'':<16}nmjax prepare-data --data NAME --from RAW_DIR",
        "",
        "The split: RAW_DIR/split.json if present, else the published lists for aist, dfaust and",
        "animals (sequences in neither are left out and counted), else 9:1 by frames. Sequences",
        "are written one at a time; a rerun skips those already written, --overwrite redoes all.",
    ]
    return "\n".join(lines)


def prepare_data(argv: list[str]) -> int:
    from nmjax.config import DATASETS
    from nmjax.data import prepare

    p = parser(
        "prepare-data", "Write a dataset in the layout <root>/<split>/{vertices,joints}/<seq>.npy"
    )
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = _downloads_help()
    p.add_argument("--data", required=True, help=f"one of {', '.join(sorted(DATASETS))}")
    p.add_argument(
        "--from",
        dest="source",
        metavar="DIR",
        type=Path,
        help="real datasets: the download as it comes (below), or one folder of mesh frames per "
        "sequence",
    )
    p.add_argument("--root", type=Path, metavar="DIR", help="output folder (default data/<name>)")
    p.add_argument("--seed", type=int, default=0, help="sampling / generation seed")
    p.add_argument(
        "--sequences",
        type=_names_or_count,
        metavar="N|NAME,...",
        help="how many sequences (the first N by name), or which (real sets; for dfaust a "
        "motion such as hips names it for every subject); default: all",
    )
    p.add_argument(
        "--subjects",
        type=_names,
        metavar="ID,...",
        help="dfaust: only these subjects (e.g. 50002,50025); default: all",
    )
    p.add_argument(
        "--body-model",
        type=Path,
        metavar="FILE",
        help="aist: the SMPL model (.pkl as downloaded, or .npz); hanco: MANO_RIGHT.pkl. Their "
        "owners license them to each user, so nmjax cannot ship them (where to get them: below)",
    )
    p.add_argument("--frames", type=int, help="frames per sequence (default: all)")
    p.add_argument("--points", type=int, default=prepare.DEFAULT_POINTS, help="points per frame")
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace what --root holds (a rerun without it keeps the prepared sequences)",
    )
    args = p.parse_args(argv)
    message = prepare_dataset(
        args.data,
        source=args.source,
        root=args.root,
        seed=args.seed,
        sequences=args.sequences,
        subjects=args.subjects,
        frames=args.frames,
        points=args.points,
        overwrite=args.overwrite,
        body_model=args.body_model,
    )
    if message is None:
        from nmjax.data.layout import dataset_root

        where = dataset_root(args.data, args.root)
        print(f"{where} already holds a prepared {args.data!r}; pass --overwrite to replace it")
        return 0
    print(message)
    return 0


def prepare_dataset(
    name: str,
    *,
    source: Path | None = None,
    root: Path | None = None,
    seed: int = 0,
    sequences: int | list[str] | None = None,
    subjects: list[str] | None = None,
    frames: int | None = None,
    points: int | None = None,
    overwrite: bool = False,
    body_model: Path | None = None,
) -> str | None:
    """Writes dataset `name` into `root` (default data/<name>): generated for a synthetic name,
    converted from the raw sequences in `source` for a real one.

    The one place that picks the writer by name: `nmjax.data.prepare` converts real sets and
    `nmjax.data.synthetic` generates the others, and neither imports the other.

    Returns:
      The line to report (a real set: its summary), or None when `root` already holds a
      prepared `name` and not `overwrite` (nothing is changed then).

    Raises:
      ValueError: an unknown name, counts below their minimum, or `source` given for a synthetic
        set / missing for a real one.
    """
    from nmjax.config import dataset_spec
    from nmjax.data import prepare
    from nmjax.data.layout import SYNTHETIC_DATASETS, clear_dataset, dataset_root

    dataset_spec(name)
    points = prepare.DEFAULT_POINTS if points is None else points
    count = sequences if isinstance(sequences, int) else None
    for flag, value, least in (("sequences", count, 1), ("frames", frames, 2)):
        if value is not None and value < least:
            raise ValueError(f"--{flag} must be >= {least}, got {value}")
    if points < 1:
        raise ValueError(f"--points must be >= 1, got {points}")
    synthetic_data = name in SYNTHETIC_DATASETS
    if synthetic_data and source is not None:
        raise ValueError(f"{name} is generated; --from is only for real datasets")
    if synthetic_data and (subjects is not None or not (sequences is None or count)):
        raise ValueError(f"{name} is generated; --sequences NAMES and --subjects pick real data")
    if synthetic_data and body_model is not None:
        raise ValueError(f"{name} is generated; --body-model is read for aist and hanco")
    if not synthetic_data and source is None:
        raise ValueError(
            f"--data {name} needs --from DIR, the download (see nmjax prepare-data --help) or "
            "the raw mesh sequences (one folder of .obj/.ply/.off frames per sequence); or use "
            "--data synth-hand"
        )
    root = dataset_root(name, root)
    if (root / "meta.json").is_file() and not overwrite:
        return None
    if not synthetic_data:
        summary = prepare.prepare_real(
            name,
            source,
            root,
            points=points,
            seed=seed,
            sequences=sequences,
            max_frames=frames,
            subjects=subjects,
            overwrite=overwrite,
            body_model=body_model,
        )
        return summary.line()
    from nmjax.data import synthetic  # lazy: only synthetic sets need the generator

    if overwrite:
        clear_dataset(root)
    synthetic.generate(name, root, num_sequences=count, frames=frames, points=points, seed=seed)
    return f"wrote {name} to {root}"


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
