"""`nmjax rig`: your own capture to a skinned, animated glTF rig in one command (`nmjax.rig`).

nmjax rig --from RAW --out RIG.glb [--mesh REST.obj] [--seq NAME] [--preset cpu]
          [--steps N | --minutes M] [--work DIR] [--up z] [--fps 30] [--units m]
          [--points 20000] [--seed 0] [--set FIELD=VALUE ...] [--overwrite] [--no-progress]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from nmjax.cli import parser, positive

EPILOG = """\
stages (each kept in --work, so a rerun of the same command picks up where it stopped):
  prepare   RAW as `nmjax prepare-data --from RAW` reads it (a folder of mesh or point
            frames, one such folder per sequence, or one (T, N, 3) .npy / .npz per sequence),
            into WORK/data
  phase 1   the keypoint detector and affinity (the `capture` spec), then Algorithm 1's
            skeleton, into the run folder WORK/skel
  motion    the detector's keypoints of every frame of --seq, mapped back into the capture's
            frame and units
  skin      Algorithm 2's weights of --mesh (default: frame 0 of a mesh capture, or frame 0's
            points of a point capture, skinned as glTF POINTS), bound in frame 0's pose
  write     RIG.glb (skinned surface, skeleton, every frame), RIG.bvh and RIG.png (the skinned
            surface over the capture's points at four frames), +Y up, in the capture's units

A bad capture (anything prepare-data refuses) is refused before any training starts."""


def rig(argv: list[str]) -> int:
    from nmjax.config import PRESETS
    from nmjax.config_io import add_override_argument
    from nmjax.data import layout
    from nmjax.data.prepare import DEFAULT_POINTS
    from nmjax.rig import DEFAULT_STEPS, RigOptions, make_rig

    p = parser(
        "rig",
        "Your capture to a skinned, animated rig: prepare, phase 1, skeleton (Algorithm 1), skin "
        "weights (Algorithm 2), the capture's own motion, written as RIG.glb and RIG.bvh.",
    )
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = EPILOG
    p.add_argument(
        "--from",
        dest="source",
        metavar="RAW",
        type=Path,
        required=True,
        help="your capture: a folder of mesh or point frames, or a folder of such folders (one "
        "a sequence) or of (T, N, 3) .npy / .npz, as `nmjax prepare-data --from` reads",
    )
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="RIG.glb",
        help="the rig, a .glb file; RIG.bvh and RIG.png are written beside it",
    )
    p.add_argument(
        "--mesh",
        type=Path,
        default=None,
        metavar="REST.obj",
        help="the mesh to skin, in frame 0's pose and place and the capture's units (default: "
        "frame 0 of a mesh capture; a point capture: frame 0's points)",
    )
    p.add_argument(
        "--seq",
        default=None,
        metavar="NAME",
        help="the sequence whose motion the rig plays (default: the first of RAW by name)",
    )
    p.add_argument(
        "--preset",
        default="default",
        choices=PRESETS,
        help="phase 1's preset of the `capture` spec: default (the paper's network, 20,000 "
        "steps), cpu (sized for 2 CPU cores, 2,200 steps), tiny (tests) (default: default)",
    )
    budget = p.add_mutually_exclusive_group()
    default_budget = "the preset's" if DEFAULT_STEPS is None else f"{DEFAULT_STEPS:,}"
    budget.add_argument(
        "--steps",
        type=int,
        default=None,
        metavar="N",
        help=f"phase 1's optimizer steps (default: {default_budget}); a rerun trains on to N",
    )
    budget.add_argument(
        "--minutes",
        type=float,
        default=None,
        metavar="M",
        help="phase 1 within M minutes: the step is timed, then as many steps as fit are trained",
    )
    p.add_argument(
        "--work",
        type=Path,
        default=None,
        metavar="DIR",
        help="the work folder (prepared capture, phase-1 run, motion; default: RIG-work beside "
        "--out); rerunning the same command reuses and resumes it",
    )
    capture = p.add_argument_group("your capture (as `nmjax prepare-data --from RAW` takes them)")
    capture.add_argument(
        "--up",
        choices=layout.UP_AXES,
        default=None,
        help=f"the capture's up axis, turned to glTF's +Y (default: {layout.DEFAULT_UP})",
    )
    capture.add_argument(
        "--fps", type=float, default=None, help="its frames per second (default: 30)"
    )
    capture.add_argument(
        "--units",
        choices=tuple(layout.UNITS),
        default=None,
        help=f"the unit of its coordinates, kept in the files (default: {layout.DEFAULT_UNITS})",
    )
    capture.add_argument(
        "--points",
        type=int,
        default=DEFAULT_POINTS,
        help=f"points per prepared frame (default: {DEFAULT_POINTS:,})",
    )
    capture.add_argument("--seed", type=int, default=0, help="sampling seed (default: 0)")
    add_override_argument(p, "override a phase-1 config field, e.g. --set model.channels=16")
    p.add_argument(
        "--overwrite", action="store_true", help="replace an existing RIG.glb / .bvh / .png"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    positive(p, args, "steps", "points")
    if args.minutes is not None and not args.minutes > 0:
        p.error(f"--minutes must be > 0, got {args.minutes}")
    result = make_rig(
        RigOptions(
            source=args.source,
            out=args.out,
            mesh=args.mesh,
            seq=args.seq,
            preset=args.preset,
            steps=args.steps,
            minutes=args.minutes,
            work=args.work,
            points=args.points,
            seed=args.seed,
            up=args.up,
            fps=args.fps,
            units=args.units,
            overrides=tuple(args.overrides),
            overwrite=args.overwrite,
            progress=not args.no_progress,
        )
    )
    print(result.summary())
    return 0
