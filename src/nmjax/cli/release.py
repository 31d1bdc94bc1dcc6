"""`nmjax import-release`: the authors' trained AIST++ model as two nmjax run folders.

    nmjax import-release CHECKPOINT.pth --options opt.pickle --run DIR [--overwrite]
                         [--example POINTS.npy]

Writes DIR/skel (phase 1) and DIR/dyn (phase 2) and prints them; see `nmjax.release`. Nothing of
PyTorch is needed or run: the checkpoint is read by a restricted unpickler.
"""

from __future__ import annotations

import json

from nmjax.cli import parser


def import_release(argv: list[str]) -> int:
    p = parser(
        "import-release",
        "Convert the authors' released checkpoint (pretrained/aist/aist_pretrained.pth and its "
        "opt.pickle) into a phase-1 run DIR/skel and a phase-2 run DIR/dyn that generate, "
        "interpolate, retarget, evaluate and view read. No PyTorch: the files are read admitting "
        "only the classes a state dict and an argparse.Namespace are made of.",
    )
    p.add_argument("checkpoint", metavar="CHECKPOINT.pth", help="the release's state dict")
    p.add_argument("--options", required=True, metavar="opt.pickle", help="its run options")
    p.add_argument("--run", required=True, metavar="DIR", help="folder for skel/ and dyn/")
    p.add_argument("--overwrite", action="store_true", help="replace an existing DIR")
    p.add_argument(
        "--example",
        default=None,
        metavar="POINTS.npy",
        help="a (T, N, >=3) point sequence whose first crop gives the keypoint intensities "
        "skeleton.json prunes by (e.g. the authors' data/demo/source/*.npy); default: the "
        "dataset's test split, which must then be prepared",
    )
    args = p.parse_args(argv)
    from nmjax import release, run_folder

    skel_run, dyn_run = release.import_release(
        args.checkpoint, args.options, args.run, overwrite=args.overwrite, example=args.example
    )
    skeleton = run_folder.read_skeleton(skel_run)
    kept = json.loads((skel_run / run_folder.SKELETON_FILE).read_text()).get("keep", [])
    record = json.loads((skel_run / release.PROVENANCE_FILE).read_text())
    print(
        f"nmjax import-release: {record['tensors']} tensors ({record['values']:,} values, sha256 "
        f"{record['sha256'][:12]}) -> K={skeleton.num_keypoints}, root {skeleton.root}, "
        f"{sum(kept)} keypoints kept"
    )
    print(f"phase 1: {skel_run}")
    print(f"phase 2: {dyn_run}")
    return 0
