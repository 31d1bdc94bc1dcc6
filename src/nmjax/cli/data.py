"""`nmjax prepare-data` and `nmjax synthesize`: datasets in the nmjax layout.

    nmjax prepare-data --from RAW --root OUT [--up z] [--fps 30] [--units m]   (your capture)
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
        f"  {'your capture':<16}nmjax prepare-data --from RAW --root OUT [--up z] [--fps 30]",
        f"  {'':<16}[--units m]: the generic spec `capture`; OUT/meta.json records --up,",
        f"  {'':<16}--fps and --units, and nmjax train-skel --root OUT reads them",
        f"  {'any real set':<16}nmjax prepare-data --data NAME --from RAW",
        "",
        "RAW holds one entry per sequence: RAW/<seq>/ with one file a frame (sorted by name,",
        "numbers as numbers), meshes (.obj/.ply/.off) or point clouds (.ply/.obj/.off with",
        "vertices only, .xyz/.txt with x y z a line, .npy of shape (N, 3), each named with its",
        "frame number), and optionally joints.npy (T, J, 3); or RAW/<seq>.npy / .npz, one",
        "(T, N, 3) array; or RAW is itself one folder of frames (one sequence, named after",
        "it). Each frame becomes --points points: a mesh sampled area-uniformly on its",
        "surface, a point cloud of N points resampled (N > P: P distinct points drawn at",
        "random; N < P: all N, then P - N drawn again), seeded by --seed, the sequence's name",
        "and the frame. NaN / inf are refused naming the file, frame and vertex.",
        "",
        "The split: RAW/split.json if present (naming only sequences RAW holds), else the",
        "published lists for aist, dfaust and animals (sequences in neither are left out and",
        "counted), else 9:1 by frames; a single sequence is cut in two, its last 10% of frames",
        "(at least one 10-frame training crop) the test sequence <seq>_test, or, too short for",
        "that, scored on a copy of itself. Sequences are written one at a time; a rerun skips",
        "those already written, --overwrite redoes all.",
    ]
    return "\n".join(lines)


def prepare_data(argv: list[str]) -> int:
    from nmjax.config import DATASETS
    from nmjax.data import layout, prepare

    p = parser(
        "prepare-data", "Write a dataset in the layout <root>/<split>/{vertices,joints}/<seq>.npy"
    )
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = _downloads_help()
    p.add_argument(
        "--data",
        default=None,
        help=f"one of {', '.join(sorted(DATASETS))} (default with --from: {layout.CAPTURE}, "
        "your own capture)",
    )
    p.add_argument(
        "--from",
        dest="source",
        metavar="DIR",
        type=Path,
        help="your capture or a real dataset: one folder of mesh or point frames (or one "
        "(T, N, 3) .npy / .npz) per sequence, or a download as it comes (below)",
    )
    p.add_argument("--root", type=Path, metavar="DIR", help="output folder (default data/<name>)")
    capture = p.add_argument_group(
        "your capture (recorded in meta.json; built-in datasets have their own)"
    )
    capture.add_argument(
        "--up",
        choices=layout.UP_AXES,
        default=None,
        help=f"the capture's up axis (default: {layout.DEFAULT_UP})",
    )
    capture.add_argument(
        "--fps",
        type=float,
        default=None,
        help=f"its frames per second (default: {DATASETS[layout.CAPTURE].fps:g})",
    )
    capture.add_argument(
        "--units",
        choices=tuple(layout.UNITS),
        default=None,
        help=f"the unit of its coordinates (default: {layout.DEFAULT_UNITS})",
    )
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
    p.add_argument(
        "--points",
        type=int,
        default=prepare.DEFAULT_POINTS,
        help=f"points per frame (default: {prepare.DEFAULT_POINTS:,})",
    )
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
        up=args.up,
        fps=args.fps,
        units=args.units,
    )
    print(message)
    return 0


def prepare_dataset(
    name: str | None,
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
    up: str | None = None,
    fps: float | None = None,
    units: str | None = None,
) -> str:
    """Writes dataset `name` into `root` (default data/<name>): generated for a synthetic name,
    converted from the raw sequences in `source` for a real one, and for `name` None (or
    "capture") the user's own capture in `source` with its `up`, `fps` and `units`.

    The one place that picks the writer by name: `nmjax.data.prepare` converts real sets and
    `nmjax.data.synthetic` generates the others, and neither imports the other.

    Returns:
      The line to report: a real set's summary, or, when `root` already holds a prepared `name`
      and not `overwrite`, that it does (nothing is changed then).

    Raises:
      ValueError: an unknown name, counts below their minimum, `source` given for a synthetic
        set / missing for a real one, --up / --fps / --units for a built-in set.
    """
    from nmjax.config import dataset_spec
    from nmjax.data import prepare
    from nmjax.data.layout import CAPTURE, SYNTHETIC_DATASETS, clear_dataset, dataset_root

    if name is None and source is None:
        raise ValueError(
            "give --from RAW, your capture (one folder of mesh or point frames per sequence), or "
            "--data NAME for a built-in dataset (e.g. --data synth-hand)"
        )
    name = CAPTURE if name is None else name
    dataset_spec(name)
    options = (("up", up), ("fps", fps), ("units", units))
    given = [f"--{flag}" for flag, value in options if value is not None]
    if given and name != CAPTURE:
        raise ValueError(
            f"{' / '.join(given)}: for your own capture only (prepared without --data); --data "
            f"{name} has its own frame rate and axes"
        )
    if name == CAPTURE and (subjects is not None or body_model is not None):
        raise ValueError(
            "--subjects and --body-model read D-FAUST / AIST++ / HanCo downloads; your capture "
            "takes --sequences NAME,..."
        )
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
            "the raw sequences (one folder of mesh or point frames per sequence); or use "
            "--data synth-hand"
        )
    root = dataset_root(name, root)
    if (root / "meta.json").is_file() and not overwrite:
        return f"{root} already holds a prepared {name!r}; pass --overwrite to replace it"
    if name == CAPTURE:
        summary = prepare.prepare_capture(
            source,
            root,
            up=up,
            fps=fps,
            units=units,
            points=points,
            seed=seed,
            sequences=sequences,
            max_frames=frames,
            overwrite=overwrite,
        )
        return summary.line()
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
