"""`nmjax view`: a run in 3D in the browser, frame by frame (see `nmjax.view`).

    nmjax view --run RUN [--split test] [--seq NAME] [--port 8080] [--host 127.0.0.1] [--up z]
               [--cond 5 --gen 25 --samples 3 --gap 10 --trajectories 16 --seed 0]
               [--record FILE.viser | FILE.html]

RUN is a phase-1 run, a phase-2 run, an `nmjax retarget` output folder or a .glb / .gltf file
of `nmjax export` (its skeleton and skinned mesh, played at the file's frame rate). The command
prints the URL and serves until Ctrl-C; on a remote machine forward the port (`ssh -L
8080:localhost:8080 HOST`). With --record it writes every frame of the sequence as a viser
recording instead and exits: FILE.html is a standalone page, FILE.viser plays in viser's static
client (`index.html?playbackPath=FILE.viser`).
"""

from __future__ import annotations

import sys
import time

from nmjax.cli import parser, positive


def view(argv: list[str]) -> int:
    from nmjax import view as viewing
    from nmjax.data.layout import SPLITS

    p = parser(
        "view",
        "Serve a run as a 3D scene in the browser (viser): a phase-1 run's points, keypoints, "
        "skeleton, ground truth and affinity; a phase-2 run's generated and interpolated "
        "motions; a retarget output's posed mesh; an exported glTF file's skinned character.",
    )
    p.add_argument(
        "--run", required=True, help="phase-1 or phase-2 run, retarget output, or .glb / .gltf file"
    )
    p.add_argument("--split", default="test", choices=SPLITS, help="whose sequences")
    p.add_argument("--seq", default=None, help="sequence to open (default: the first)")
    p.add_argument("--host", default="127.0.0.1", help="0.0.0.0 serves every interface")
    p.add_argument("--port", type=int, default=8080, help="0: any free port")
    p.add_argument("--up", choices=viewing.UP_AXES, default=None, help="default: the run's data")
    p.add_argument(
        "--record",
        default=None,
        metavar="FILE",
        help="write every frame as a viser recording (FILE.viser, or FILE.html: a standalone "
        "page) and exit; the server meanwhile takes any free port",
    )
    tasks = p.add_argument_group("phase-2 runs", "as `nmjax generate` and `nmjax interpolate`")
    tasks.add_argument("--cond", type=int, default=5, help="T_cond observed frames")
    tasks.add_argument("--gen", type=int, default=25, help="T_gen generated frames")
    tasks.add_argument("--samples", type=int, default=3, help="generated continuations S")
    tasks.add_argument("--gap", type=int, default=10, help="frames between the keyframes")
    tasks.add_argument("--trajectories", type=int, default=16, help="rollouts to choose from")
    tasks.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    positive(p, args, "cond", "gen", "samples", "gap", "trajectories")
    if not 0 <= args.port <= 65535:
        p.error(f"--port must be in 0..65535, got {args.port}")

    settings = vars(args).copy()
    folder, record = settings.pop("run"), settings.pop("record")
    if record is not None:
        settings["port"] = 0  # nobody connects to a recording's server
    try:
        viewing.import_viser()
    except ImportError as err:
        print(f"nmjax view: {err}", file=sys.stderr)
        return 2
    viewer = viewing.open_view(folder, **settings)
    try:
        if record is not None:
            print(f"nmjax view: wrote {viewer.record(record)}")
            return 0
        print(f"nmjax view: {viewer.kind} {folder} at {viewer.url()} (Ctrl-C stops)")
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        return 0
    finally:
        viewer.stop()
