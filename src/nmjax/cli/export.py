"""`nmjax export`: a run's rig and motion as glTF 2.0 or BVH (see `nmjax.export`).

    nmjax export --run RUN --out FILE.glb|FILE.gltf|FILE.bvh [--seq NAME] [--sample S]
                 [--method NAME] [--split test] [--fps F] [--up x|y|z] [--seed 0] [--unrefined]
                 [--overwrite]

RUN is an `nmjax retarget` output (the skinned target mesh and its motion), an `nmjax generate`
or `nmjax interpolate` output (one motion: --seq picks the input, --sample the continuation,
--method the interpolation), or a phase-2 or phase-1 run with --seq NAME (the model's
reconstruction of that sequence, or the detector's keypoints of it; for a phase-1 sequence that
`nmjax refine` refined, its refined skeleton unless --unrefined).
"""

from __future__ import annotations

from nmjax.cli import parser


def export(argv: list[str]) -> int:
    from nmjax.export import FORMATS, UP_AXES, Options, export_run
    from nmjax.export.sources import REFINED_SUFFIX

    p = parser(
        "export",
        "Write the discovered rig (skeleton, skin, motion) as glTF 2.0 (.glb, .gltf) or BVH "
        "(.bvh), joints named joint_<k> after their keypoint index.",
    )
    p.add_argument(
        "--run", required=True, help="run folder, or retarget / generate / interpolate output"
    )
    p.add_argument("--out", required=True, help=f"output file: {', '.join(FORMATS)}")
    p.add_argument("--seq", default=None, help="sequence (runs) or input (task outputs)")
    p.add_argument("--sample", type=int, default=None, help="generate output: sample (default 0)")
    p.add_argument("--method", default=None, help="interpolate output: method (default Ours)")
    p.add_argument("--split", default="test", choices=("train", "test"), help="runs: whose --seq")
    p.add_argument("--fps", type=float, default=None, help="frames per second (default: the run's)")
    p.add_argument(
        "--up",
        choices=UP_AXES,
        default=None,
        help="the data's up axis (default: the run's); the file is +Y up",
    )
    p.add_argument("--seed", type=int, default=0, help="phase-2 runs: posterior samples")
    p.add_argument(
        "--unrefined",
        action="store_true",
        help="phase-1 runs: the keypoints even where `nmjax refine` stored a refined skeleton",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    args = p.parse_args(argv)
    if args.fps is not None and not args.fps > 0:
        p.error(f"--fps must be > 0, got {args.fps}")
    options = Options(args.seq, args.sample, args.method, args.split, args.seed, args.unrefined)
    out, rig = export_run(
        args.run, args.out, options=options, fps=args.fps, up=args.up, overwrite=args.overwrite
    )
    mesh = "" if rig.vertices is None else f", mesh of {len(rig.vertices)} vertices"
    if rig.vertices is not None and out.suffix.lower() == ".bvh":
        mesh = " (BVH holds no mesh: export to .glb for the skinned mesh)"
    refined = " (the refined skeleton)" if rig.name.endswith(REFINED_SUFFIX) else ""
    print(
        f"nmjax export: wrote {out}: {len(rig.joints)} joints, {rig.num_frames} frames at "
        f"{rig.frame_rate:g} fps{mesh}{refined}"
    )
    return 0
