"""Paper Tables 11-12: interpolation M-CD of Ours, VRNN, Lerp and Slerp, at CPU scale.

    JAX_PLATFORMS=cpu .venv/bin/python experiments/table11_12_interpolation.py \
        --data synth-hand synth-human --dyn-steps 3000

Per dataset: the phase-1 run of the `cpu` preset at seed 0 (`paper_phase1.py`'s row, trained
here if its run folder is missing), a phase-2 "nm" run and a positional "vrnn" run on it, then
`nmjax.evaluate.evaluate_run` (SR = 3 ... 30, 95% CI over test sequences). Writes
experiments/results/table11_12_interpolation.md and table11_12_<data>.png (with
--keypoints-only table11_12_keypoints.md), stamped with the commit, machine and metric
definitions (`nmjax.provenance`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import exp_common as ec
import paper_phase1

from nmjax import provenance, runs, viz
from nmjax.evaluate import (
    INTERPOLATION_METRICS,
    SAMPLING_RATES,
    evaluate_interpolation,
    evaluate_run,
    interpolation_table,
)
from nmjax.runs import Detector
from nmjax.tasks import Interpolators

PAPER = (
    "Paper Table 11 (HanCo) averages: Ours 2.64, VRNN 2.98, Lerp 5.07, Slerp 4.52; Table 12 "
    "(D-FAUST): Ours 2.88, VRNN 2.96, Lerp 3.67, Slerp 3.65 (scale not stated in the paper)."
)


def trained_runs(
    data: str, args: argparse.Namespace, trained: dict[str, Path]
) -> tuple[Path, Path, Path]:
    """The phase-1 "ours", phase-2 "nm" and phase-2 "vrnn" runs of `data` (trained if needed).

    Each is also recorded in `trained` under "<data> phase 1" / "<data> nm" / "<data> vrnn" for
    the training note of the results file.
    """
    skel = paper_phase1.trained_run(paper_phase1.RowKey(data, 0, "preset"))
    nm = ec.dyn_run(data, "nm", skel, args.dyn_steps)
    vrnn = ec.dyn_run(data, "vrnn", skel, args.dyn_steps)
    trained.update({f"{data} phase 1": skel, f"{data} nm": nm, f"{data} vrnn": vrnn})
    return skel, nm, vrnn


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", nargs="+", default=["synth-hand", "synth-human"])
    parser.add_argument("--dyn-steps", type=int, default=3000)
    parser.add_argument("--rates", type=int, nargs="+", default=list(SAMPLING_RATES))
    parser.add_argument("--trajectories", type=int, default=16)
    parser.add_argument("--max-segments", type=int, default=4)
    parser.add_argument(
        "--keypoints-only",
        action="store_true",
        help="no decoding: only the in-between keypoint error (table11_12_keypoints.md)",
    )
    args = parser.parse_args()
    if args.keypoints_only:
        keypoints_only(args)
        return
    stamp = provenance.stamp({"interpolation": INTERPOLATION_METRICS["interpolation"]})
    sections, trained = [], {}
    for data in args.data:
        _, nm, vrnn = trained_runs(data, args, trained)
        res = evaluate_run(
            nm,
            vrnn_run=vrnn,
            out=ec.RUNS / f"eval-{data}",
            rates=tuple(args.rates),
            trajectories=args.trajectories,
            max_segments=args.max_segments,
            max_crops=1,
        )
        mcd = res["interpolation"]
        viz.plot_mcd(ec.RESULTS / f"table11_12_{data}.png", mcd, title=f"{data}: M-CD x1e3")
        provenance.stamp_png(ec.RESULTS / f"table11_12_{data}.png", stamp)
        lines = interpolation_table(mcd, data) + [f"![M-CD](table11_12_{data}.png)", ""]
        sections.append("\n".join(lines))
    provenance.write_markdown(
        ec.RESULTS / "table11_12_interpolation.md",
        "# Tables 11-12: interpolation M-CD x1e3 (Eq. 22; 95% CI over test sequences)\n\n"
        f"{ec.training_header(trained)}\n" + "\n".join(sections) + f"\n{PAPER}\n",
        stamp,
    )


def keypoints_only(args) -> None:
    """The decoder-free check: squared error of the in-between keypoints, every method."""
    from flax import nnx

    stamp = provenance.stamp(
        {"interpolation_keypoints": INTERPOLATION_METRICS["interpolation_keypoints"]}
    )
    sections, trained = [], {}
    for data in args.data:
        skel, nm, vrnn = trained_runs(data, args, trained)
        nm_cfg = runs.phase2_runs(nm, vrnn)[0]  # both trained on the same inputs
        interp = Interpolators(
            nnx.split(runs.restore_dynamics(nm)),
            nnx.split(runs.restore_dynamics(vrnn)),
            args.trajectories,
        )
        errors = evaluate_interpolation(
            Detector.load(skel),
            interp,
            runs.load_trajectories(skel, "test") if nm_cfg.inputs == "sequence" else None,
            tuple(args.rates),
            max_segments=args.max_segments,
            voxels=False,
            frames=nm_cfg.frames,
        )["interpolation_keypoints"]
        sections += [f"## {data}", ""] + interpolation_table(
            errors, "In-between keypoint error (sum over K of squared xyz; 95% CI over sequences)"
        )
    provenance.write_markdown(
        ec.RESULTS / "table11_12_keypoints.md",
        "# Tables 11-12, decoder-free: in-between keypoint error of the interpolations\n\n"
        f"{ec.training_header(trained)}\n" + "\n".join(sections) + "\n",
        stamp,
    )


if __name__ == "__main__":
    main()
