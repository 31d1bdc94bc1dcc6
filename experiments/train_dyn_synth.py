"""Phase 2 on a synthetic body, with learning curves written to experiments/results/.

Uses a phase-1 run when one is given (--skel-run, contract C10), with the phase-2 inputs of the
preset ("crop": its detector on every crop) unless --inputs says otherwise. Without one it builds
an *oracle* stand-in: the generator's ground-truth joints (normalised per sequence with the point
cloud's bounding box, alpha = 1) and its true parent tree, written in the C10 layout and read as
"sequence" inputs (there is no detector). The oracle measures the dynamics module alone; the
result file says which input was used.

    JAX_PLATFORMS=cpu .venv/bin/python experiments/train_dyn_synth.py --data synth-arm

Writes experiments/results/train_dyn_synth_<data>.json (configuration, final validation,
steps/s, curves) and .png (training loss; validation reconstruction against "repeat the last pose";
generation against "hold the last observed pose"), both stamped with the commit, machine and
metric definitions (`nmjax.provenance`). (`train_dyn_<body>.*`, without "synth_", are the
paper results' curves, rendered by `phase2_tables.py` from `paper_phase2.py`'s rows.)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from nmjax import provenance, run_folder, viz
from nmjax.config import DYN_INPUTS, dyn_preset
from nmjax.config_io import config_to_dict, replace_fields
from nmjax.data import bodies, layout, synthetic
from nmjax.data.normalize import normalize_sequence
from nmjax.skeleton import skeleton_from_parents
from nmjax.train import dyn, metric_log

RESULTS = Path(__file__).parent / "results"
METRICS = {
    "train/recon": "Eq. 3 reconstruction with the training rule (best of S posterior samples)",
    "train/last_pose, val/last_pose": "Eq. 3 of predicting x_t by x_{t-1} on the same frames",
    "val/recon": "posterior reconstruction error of one sample, frames 2..T",
    "val/recon_best": "the same, best of S samples",
    "val/gen": "error of the prior rollout after T/4 observed frames on the generated frames",
    "val/gen_hold": "the same for holding the last observed pose",
    "train_steps_per_s_median": "median of the logged training steps/s, the first left out",
}


def oracle_run(data: str, folder: Path, sequences: int, seed: int) -> Path:
    """A phase-1 run folder (`nmjax.run_folder`'s skeleton.json and keypoints_<split>.npz) from
    the ground-truth joints of `sequences` generated sequences."""
    body = bodies.get_body(data)
    splits = layout.split_names(sequences)
    rng = np.random.default_rng(seed)
    children = iter(rng.spawn(sequences))
    for split in ("train", "test"):
        trajectories = {}
        for name in splits[split]:
            frames = int(rng.integers(body.frames[0], body.frames[1] + 1))
            seq = synthetic.simulate(data, frames, points=2000, rng=next(children))
            _, joints = normalize_sequence(seq.vertices, seq.joints)
            alpha = np.ones((*joints.shape[:2], 1), np.float32)
            trajectories[name] = np.concatenate([joints, alpha], axis=-1)
        run_folder.write_trajectories(run_folder.keypoints_file(folder, split), trajectories)
    # Breadth first from the root, children by index.
    run_folder.write_skeleton(folder, skeleton_from_parents(np.asarray(body.parents)))
    return folder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="synth-arm", choices=sorted(bodies.BODIES))
    parser.add_argument("--skel-run", default=None, help="a phase-1 run (default: oracle input)")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--steps", type=int, default=6000)
    parser.add_argument("--models", nargs="+", default=["nm", "vrnn"])
    parser.add_argument("--sequences", type=int, default=200)
    parser.add_argument("--workdir", default="runs/experiments")
    parser.add_argument(
        "--inputs", choices=DYN_INPUTS, default=None, help="phase-2 inputs of a --skel-run"
    )
    args = parser.parse_args()
    stamp = provenance.stamp(METRICS)
    workdir = Path(args.workdir)
    inputs = args.inputs or dyn_preset(args.data, args.preset).data.inputs
    if args.skel_run is None:
        skel_run = oracle_run(args.data, workdir / f"oracle-{args.data}", args.sequences, seed=0)
        source = "oracle: ground-truth joints of the synthetic generator (alpha = 1)"
        inputs = "sequence"  # the oracle has no detector to run on crops
    else:
        skel_run = Path(args.skel_run)
        source = f"phase-1 run {args.skel_run}, phase-2 inputs '{inputs}'"
    curves, summary = {}, {}
    for model in args.models:
        cfg = dyn_preset(args.data, args.preset)
        cfg = replace_fields(
            cfg,
            data=dataclasses.replace(cfg.data, inputs=inputs),
            skel_run=str(skel_run),
            model=dataclasses.replace(cfg.model, model=model),
            steps=args.steps,
            val_every=max(args.steps // 10, 1),
            ckpt_every=args.steps,
            run=str(workdir / f"dyn-{args.data}-{model}-{args.preset}"),
        )
        run_dir = dyn.train_dynamics(cfg, overwrite=True, progress=False).run
        records = metric_log.read_metrics(run_dir)
        curves[model] = records
        rates = [r["train/steps_per_s"] for r in records if "train/steps_per_s" in r][1:]
        final = next(r for r in reversed(records) if "val/recon" in r)
        summary[model] = {
            "config": config_to_dict(cfg),
            "final_validation": final,
            "train_steps_per_s_median": float(np.median(rates)) if rates else None,
        }
        print(json.dumps({model: summary[model]["final_validation"]}), flush=True)
    RESULTS.mkdir(parents=True, exist_ok=True)
    stem = RESULTS / f"train_dyn_synth_{args.data}"
    provenance.write_json(
        stem.with_suffix(".json"),
        {
            "data": args.data,
            "input": source,
            "sequences": args.sequences if args.skel_run is None else None,
            "preset": args.preset,
            **summary,
            "curves": curves,
        },
        stamp,
    )
    viz.plot_phase2_curves(stem.with_suffix(".png"), curves, f"phase 2 on {args.data} ({source})")
    provenance.stamp_png(stem.with_suffix(".png"), stamp)
    print(f"wrote {stem}.json and {stem}.png")


if __name__ == "__main__":
    main()
