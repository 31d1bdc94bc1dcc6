"""What phase 2's "crop" inputs cost: the whole run against "sequence", the detector's inference
rate against the phase-1 step's, and the detector passes of an AIST++-sized run (counted).

    JAX_PLATFORMS=cpu .venv/bin/python experiments/phase2_inputs_cost.py --skel-run SKEL \
        [--data synth-arm] [--steps 3000] [--bench-steps 10]

1. `nmjax train-dyn --preset cpu` on the phase-1 run SKEL with `data.inputs=sequence`, then
   with `data.inputs=crop`, each a fresh process timed from start to exit (compilation
   included), and the crops the crop run detected (`crops_detected` of its last progress line);
2. `nmjax bench --phase skel detect --preset cpu`: the detector's frames/s on phase-2 crops
   (normalising and voxelising included) against the phase-1 train step's;
3. counted, not run: the detector passes of phase 2 on AIST++ at the default preset (150 epochs
   of ceil(1,227 / 16) steps of 16 crops) against the release's (one crop per training sequence
   per epoch), for the crop starts `--aist-frames` frames a sequence gives.

Run it on a quiet machine: the two train-dyn runs and the two bench rows follow each other.
Writes experiments/results/phase2_inputs_cost.{json,md}, stamped (`nmjax.provenance`).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from nmjax import provenance
from nmjax.config import dyn_preset
from nmjax.data import splits

RESULTS = Path(__file__).parent / "results"
METRICS = {
    "run_s": "wall seconds of `nmjax train-dyn --preset cpu` in a fresh process, start to exit",
    "crop_over_sequence": "the crop run's wall seconds / the sequence run's",
    "detect_frames_per_s": "`nmjax bench --phase detect`: phase-2 crop frames through the "
    "detector per second, normalising and voxelising included",
    "skel_frames_per_s": "`nmjax bench --phase skel`: phase-1 training frames per second "
    "(forward and backward)",
    "aist_detector_crops": "crops phase 2 detects on AIST++: expected distinct starts among the "
    "draws (S (1 - (1 - 1/S)^D)), and its bound min(S, D)",
}


def timed(argv: list[str]) -> tuple[float, str]:
    """(wall seconds, stderr) of one `nmjax` command in a fresh process; fails loudly."""
    tic = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "nmjax.cli", *argv], capture_output=True, text=True, check=False
    )
    seconds = time.perf_counter() - tic
    if done.returncode != 0:
        raise SystemExit(f"`nmjax {' '.join(argv)}` failed: {done.stderr.strip()[-500:]}")
    return seconds, done.stderr


def aist_count(frames_per_sequence: int) -> dict[str, float]:
    """Detector crops of phase 2 on AIST++ at the default preset, counted."""
    cfg = dyn_preset("aist", "default")
    sequences = len(set(splits.read_published("aist")["train"]))
    span = (cfg.data.frames - 1) * 2 + 1  # the release's sample rate 2
    starts = sequences * max(frames_per_sequence - span + 1, 1)
    batch = cfg.data.batch_size
    draws = cfg.loop.epochs * math.ceil(sequences / batch) * batch
    expected = starts * (1.0 - math.exp(draws * math.log1p(-1.0 / starts)))
    return {
        "training_sequences": sequences,
        "frames_per_sequence": frames_per_sequence,
        "crop_starts": starts,
        "draws": draws,
        "expected_detected": expected,
        "bound_detected": min(starts, draws),
        "release_detected": cfg.loop.epochs * sequences,
        "up_front_detected": starts,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--skel-run", required=True, type=Path)
    parser.add_argument("--data", default="synth-arm")
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--bench-steps", type=int, default=10)
    # AIST++: 5.2 hours of 60 fps motion over 1,408 sequences, about 800 frames a sequence.
    parser.add_argument("--aist-frames", type=int, default=800)
    args = parser.parse_args()
    stamp = provenance.stamp(METRICS)
    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        for inputs in ("sequence", "crop"):
            argv = ["train-dyn", "--data", args.data, "--skel-run", str(args.skel_run)]
            argv += ["--preset", "cpu", "--steps", str(args.steps), "--run", f"{tmp}/{inputs}"]
            seconds, err = timed([*argv, "--set", f"data.inputs={inputs}"])
            found = re.findall(r"crops_detected=(\d+)/(\d+)", err)
            runs[inputs] = {"run_s": seconds}
            if found:
                runs[inputs]["crops_detected"], runs[inputs]["crop_starts"] = map(int, found[-1])
            print(inputs, runs[inputs], flush=True)
        out = f"{tmp}/bench.json"
        argv = ["bench", "--phase", "skel", "detect", "--preset", "cpu", "--data", args.data]
        timed([*argv, "--steps", str(args.bench_steps), "--warmup", "2", "--out", out])
        rows = {row["phase"]: row for row in json.loads(Path(out).read_text())["rows"]}
    result = {
        "runs": runs,
        "crop_over_sequence": runs["crop"]["run_s"] / runs["sequence"]["run_s"],
        "detect_frames_per_s": rows["detect"]["frames_per_s"],
        "skel_frames_per_s": rows["skel"]["frames_per_s"],
        "detect_over_skel": rows["detect"]["frames_per_s"] / rows["skel"]["frames_per_s"],
        "bench_rows": rows,
        "aist": aist_count(args.aist_frames),
    }
    provenance.write_json(RESULTS / "phase2_inputs_cost.json", result, stamp)
    a = result["aist"]
    text = (
        '# What phase 2\'s "crop" inputs cost\n\n'
        f"Command: `{stamp['command']}`\n\n"
        "| measure | value |\n|---|---|\n"
        f"| `train-dyn --preset cpu` on {args.data}, {args.steps} steps, inputs=sequence | "
        f"{runs['sequence']['run_s']:.0f} s |\n"
        f"| the same, inputs=crop | {runs['crop']['run_s']:.0f} s "
        f"({runs['crop'].get('crops_detected', '?')} of {runs['crop'].get('crop_starts', '?')} "
        "crops detected) |\n"
        f"| crop / sequence | {result['crop_over_sequence']:.2f}x |\n"
        f"| detector on phase-2 crops (voxelising included) | "
        f"{result['detect_frames_per_s']:.1f} frames/s |\n"
        f"| phase-1 train step (cpu preset) | {result['skel_frames_per_s']:.1f} frames/s |\n"
        f"| detector / train step | {result['detect_over_skel']:.2f}x |\n"
        f"| AIST++ (counted): {a['training_sequences']} training sequences of about "
        f"{a['frames_per_sequence']} frames, {a['crop_starts']:,} crop starts, {a['draws']:,} "
        f"draws | detected: expected {a['expected_detected']:,.0f} (at most "
        f"{a['bound_detected']:,}); the release: {a['release_detected']:,}; every start up "
        f"front: {a['up_front_detected']:,} |\n"
    )
    provenance.write_markdown(RESULTS / "phase2_inputs_cost.md", text, stamp)
    print(text)


if __name__ == "__main__":
    main()
