"""The task commands on a phase-2 run folder (which records its phase-1 run):

    nmjax generate    --run RUN [--cond 5] [--gen 25] [--samples 3] [--inputs 2] [--voxels]
                      (--gen 300 works; past the end of a test sequence its observed panel holds)
    nmjax interpolate --run RUN [--gap 10] [--trajectories 16] [--inputs 2] [--vrnn-run RUN2]
    nmjax retarget    --run RUN --target MESH [--source SEQ] [--frames N (default: all)]

Each takes its inputs from the phase-1 run's exported test keypoints, or with `--source-file
POINTS.npy [--source-rate N]` from a point-sequence file (T, N, >= 3) normalised and detected as
one crop, as the release's demos do (an imported release needs no dataset then). Each writes into
`--out` (default `RUN/<command>`); see `nmjax.tasks.run_generate`, `run_interpolate` and
`run_retarget`.
"""

from __future__ import annotations

from nmjax.cli import Parser, parser, positive


def _parser(command: str, description: str, out: str | None = None) -> Parser:
    p = parser(command, description)
    p.add_argument("--run", required=True, help="phase-2 run folder (train-dyn, model nm)")
    p.add_argument(
        "--out", default=None, help=f"output folder (default: {out or f'RUN/{command}'})"
    )
    p.add_argument("--seed", type=int, default=0, help="sampling seed (default: 0)")
    p.add_argument(
        "--source-file",
        default=None,
        metavar="POINTS.npy",
        help="take the input motion from this (T, N, >=3) point sequence instead of the test set",
    )
    p.add_argument(
        "--source-rate",
        type=int,
        default=None,
        metavar="N",
        help="with --source-file: every N-th frame (default: the run's sample rate)",
    )
    return p


def _run(p: Parser, argv: list[str], function: str, positive_options: tuple[str, ...]) -> int:
    """Parses `argv`, checks the `positive_options` and calls `nmjax.tasks.<function>`.

    Every option of the parser is passed under its destination name, so the parser and the task
    function must agree on names.
    """
    args = p.parse_args(argv)
    positive(p, args, *positive_options)
    if getattr(args, "source", None) is not None and args.source_file is not None:
        p.error("give either --source NAME or --source-file PATH, not both")
    if args.source_rate is not None and args.source_file is None:
        p.error("--source-rate applies to --source-file only")
    from nmjax import tasks

    out = getattr(tasks, function)(**vars(args))
    print(f"{p.prog}: wrote {out}")
    return 0


def generate(argv: list[str]) -> int:
    p = _parser("generate", "Sample T_gen future frames after T_cond observed frames.")
    p.add_argument("--cond", type=int, default=5, help="T_cond observed frames")
    p.add_argument("--gen", type=int, default=25, help="T_gen generated frames")
    p.add_argument("--samples", type=int, default=3, help="futures per input")
    p.add_argument("--inputs", type=int, default=2, help="test sequences used as inputs")
    p.add_argument("--voxels", action="store_true", help="also decode voxels (phase-1)")
    return _run(p, argv, "run_generate", ("cond", "gen", "samples", "inputs", "source_rate"))


def interpolate(argv: list[str]) -> int:
    p = _parser("interpolate", "Interpolate between keyframes 0 and GAP of test sequences.")
    p.add_argument("--gap", type=int, default=10, help="frames between the keyframes (SR)")
    p.add_argument("--trajectories", type=int, default=16, help="rollouts to choose from")
    p.add_argument("--inputs", type=int, default=2, help="test sequences")
    p.add_argument("--vrnn-run", default=None, help="positional VRNN run for the baseline")
    return _run(p, argv, "run_interpolate", ("gap", "trajectories", "inputs", "source_rate"))


def retarget(argv: list[str]) -> int:
    p = _parser(
        "retarget",
        "Retarget a test motion onto a mesh (Eqs. 24-25, LBS).",
        out="RUN/retarget-TARGET, TARGET the mesh's file name without its suffix",
    )
    p.add_argument(
        "--target", required=True, help="target mesh with faces (.obj, .ply, .off, .stl, ...)"
    )
    p.add_argument("--source", default=None, help="test sequence name (default: the first by name)")
    p.add_argument(
        "--frames",
        type=int,
        default=None,
        help="frames of the source motion, from its first (default: every frame of the source)",
    )
    p.add_argument(
        "--points",
        type=int,
        default=20000,
        help="points sampled on the mesh to detect its joints (default: 20000)",
    )
    return _run(p, argv, "run_retarget", ("frames", "points", "source_rate"))
