"""`nmjax evaluate --run RUN`: the paper's quantitative tables (see `nmjax.evaluate`)."""

from __future__ import annotations

from nmjax.cli import parser, positive


def _text(values: tuple[int, ...]) -> str:
    return ",".join(map(str, values))


def _integers(text: str, option: str, minimum: int) -> tuple[int, ...]:
    """'3,5,10' -> (3, 5, 10); a ValueError naming `option` unless all are >= `minimum`."""
    try:
        values = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        values = ()
    if not values or min(values) < minimum:
        raise ValueError(f"{option} must be comma-separated integers >= {minimum}, got {text!r}")
    return values


def evaluate(argv: list[str]) -> int:
    from nmjax import evaluate as ev

    p = parser(
        "evaluate",
        "SC-score, 4D-tracking Chamfer and interpolation M-CD (paper Tables 1, 2, 11, 12) of a "
        "phase-2 run (or the phase-1 metrics of a phase-1 run); on data with ground-truth "
        "joints also the skeleton against the true one (joint distance, joint coverage, edge "
        "precision, bone recall, distinct nodes, tree edit distance, CD-J2J / J2B / B2B); the "
        "fit error of the run's rig to its test crops; with --generation, the generation "
        "measures of a phase-2 run instead.",
    )
    p.add_argument("--run", required=True, help="phase-2 ('nm') or phase-1 run folder")
    p.add_argument("--vrnn-run", default=None, help="positional VRNN run (default: found)")
    p.add_argument("--out", default=None, help="output folder (default RUN/eval)")
    p.add_argument("--rates", default=_text(ev.SAMPLING_RATES), help="sampling rates SR")
    p.add_argument("--trajectories", type=int, default=16, help="rollouts per keyframe pair")
    p.add_argument("--max-segments", type=int, default=4, help="keyframe pairs per sequence")
    p.add_argument("--max-crops", type=int, default=8, help="phase-1 test crops per sequence")
    p.add_argument("--seed", type=int, default=0)
    gen = p.add_argument_group(
        "generation", "--generation writes RUN/eval/generation.{json,md,png} instead of the tables"
    )
    gen.add_argument(
        "--generation",
        action="store_true",
        help="only the generation evaluation: diversity, bone-length error, set distance",
    )
    gen.add_argument("--horizons", default=_text(ev.GEN_HORIZONS), help="generated frames N")
    gen.add_argument("--samples", type=int, default=10, help="futures per conditioning clip")
    gen.add_argument("--cond", type=int, default=5, help="T_cond conditioning frames")
    gen.add_argument("--clips", type=int, default=4, help="conditioning clips per test sequence")
    gen.add_argument(
        "--real-keypoints",
        default=None,
        metavar="NPZ",
        help="keypoint sequences to cut the real clips from (default: the test keypoints); "
        "longer sequences give real clips at long horizons",
    )
    args = p.parse_args(argv)
    positive(p, args, "trajectories", "max_segments", "max_crops", "samples", "cond", "clips")
    rates = _integers(args.rates, "--rates", 1)
    horizons = _integers(args.horizons, "--horizons", 2)

    if args.generation:
        results = ev.evaluate_generation_run(
            args.run,
            vrnn_run=args.vrnn_run,
            out=args.out,
            horizons=horizons,
            cond=args.cond,
            samples=args.samples,
            clips=args.clips,
            seed=args.seed,
            real_keypoints=args.real_keypoints,
        )
        print(ev.generation_markdown(results))
        return 0
    results = ev.evaluate_run(
        args.run,
        vrnn_run=args.vrnn_run,
        out=args.out,
        rates=rates,
        trajectories=args.trajectories,
        max_segments=args.max_segments,
        max_crops=args.max_crops,
        seed=args.seed,
    )
    print(ev.markdown_tables(results))
    return 0
