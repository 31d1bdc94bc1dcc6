"""The articulated refinement after phase 1 against the skeleton it starts from, on phase-1 runs.

    JAX_PLATFORMS=cpu .venv/bin/python experiments/refine_bench.py \
        [--run RUN ...] [--data synth-arm synth-hand synth-human synth-quadruped] [--seeds 0 1] \
        [--iters N] [--out experiments/results] [--allow-dirty]

A row is one phase-1 run: every test sequence refined (`nmjax.export.refine.refine_sequence`,
the settings of `nmjax refine`) and scored against the unrefined rig of the same run, the one
`nmjax export` makes of the keypoints (kept nodes, rest pose frame 0, swing rotations, Algorithm
2's weights), on the same frames in the same cube (each whole sequence normalised with one box,
as keypoints_test.npz was detected):

- joint distance: every true joint to its nearest joint of the rig, mean over joints and frames
  (`metrics.joint_distance`, the cube's units);
- CD-J2J, CD-J2B, CD-B2B x1e-2 (`metrics.skeleton_chamfers`, each frame's body box scaled to
  [-0.5, 0.5]^3);
- the rig's fit error x1e4 in the cube and in the capture's units (`metrics.rig_fit_error`: the
  same rest surface, frame 0's points, skinned by each rig against every frame's points);
- bone-length variation (`metrics.bone_length_variation`) and the tree edit distance to the true
  tree (`metrics.tree_edit_distance`; the refinement keeps the tree);
- the refinement's seconds per sequence (compilation included), and once per run the seconds of
  a 60-frame, 8,000-point sequence (the first test sequence, its frames played back and forth to
  60 and 8,000 of its points, the same in every frame), to be measured on 2 cores.

The runs are the ones given by path with --run, or by default the `cpu`-preset runs of
`paper_phase1.py` on the four synthetic bodies at seeds 0 and 1 (`runs/exp/skel-<body>-s<seed>-
preset`), trained first where missing. Rows go to `<out>/refine_<body>.json` (`nmjax.rows`: a
row is kept, and its run not refined again, while it is what this script computes now), and each
body's `refine_<body>.md` (the table and the targets) and `refine_<body>.png` (unrefined and
refined skeletons over the same frames, a row pair per seed) are rendered from them, stamped
(`nmjax.provenance`). Targets (the issue's; `TARGETS`): on every body at both seeds, joint
distance at least 30% lower and CD-J2J lower; the fit error at most half the unrefined rig's;
bone-length variation below 1e-6; the tree edit distance no worse; at most 2 minutes for the
60-frame, 8,000-point sequence on 2 cores.

Run it on a quiet machine with 2 cores (`taskset -c 0,1`) for the timings.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np

from nmjax import metrics, provenance, rows, run_folder
from nmjax.config import SkelTrainConfig
from nmjax.data.layout import read_meta
from nmjax.export.refine import point_subset, refine_sequence, sequence_frames, unrefined_rig
from nmjax.skeleton_refine import RefineSettings
from nmjax.viz import draw_pruned_tree, save_figure  # importing nmjax.viz selects Agg

RESULTS = Path(__file__).parent / "results"
BODIES = ("synth-arm", "synth-hand", "synth-human", "synth-quadruped")
SEEDS = (0, 1)
# The last commit that changed what a row computes (the refinement or its scoring).
SINCE = "HEAD"
# The sequence the time target is about: 60 frames of 8,000 points, on 2 cores.
TIMING_FRAMES, TIMING_POINTS, TIMING_SECONDS = 60, 8000, 120.0
# Points per frame kept for the pictures, and the frames drawn.
PICTURE_POINTS, PICTURE_FRAMES = 600, 4
MEASURES = {
    "joint_distance": "mean over true joints and frames of the distance to the rig's nearest "
    "joint, in the sequence's cube [-1, 1]^3 (`metrics.joint_distance`)",
    "cd_j2j": "CD-J2J x1e-2, each frame's body box scaled to [-0.5, 0.5]^3 "
    "(`metrics.skeleton_chamfers`)",
    "cd_j2b": "CD-J2B x1e-2, as CD-J2J",
    "cd_b2b": "CD-B2B x1e-2, as CD-J2J",
    "rig_fit_cd": "the rig's fit error x1e4 in the cube: frame 0's surface (the refinement's "
    "rest surface) skinned by the rig against every frame's points (at most 4,096, "
    "`metrics.rig_fit_error`)",
    "rig_fit_cd_capture": "the same fit error in the capture's units, squared",
    "bone_length_variation": "std over frames of every bone's length / its mean, mean over bones "
    "(`metrics.bone_length_variation`)",
    "tree_edit_distance": "APTED tree edit distance of the rig's tree to the true tree, unit "
    "insert and delete (`metrics.tree_edit_distance`)",
    "seconds": "the refinement's wall seconds per sequence, compilation included",
}
METRICS = {
    **MEASURES,
    "timing_seconds": f"wall seconds of refining a {TIMING_FRAMES}-frame, {TIMING_POINTS}-point "
    "sequence (the first test sequence played back and forth, the same points in every frame), "
    "compilation included",
}
# name -> (description, the test on (unrefined, refined)).
TARGETS = {
    "joint_distance": ("at least 30% lower", lambda u, r: r <= 0.7 * u),
    "cd_j2j": ("lower", lambda u, r: r < u),
    "rig_fit_cd": ("at most half the unrefined rig's", lambda u, r: r <= 0.5 * u),
    "bone_length_variation": ("below 1e-6", lambda u, r: r < 1e-6),
    "tree_edit_distance": ("no worse", lambda u, r: r <= u),
    "timing_seconds": (
        f"at most {TIMING_SECONDS:.0f} s for {TIMING_FRAMES} frames x {TIMING_POINTS} points "
        "on 2 cores",
        lambda u, r: r <= TIMING_SECONDS,
    ),
}
SCORE_KEYS = tuple(k for k in MEASURES if k != "seconds")


# --- scoring ------------------------------------------------------------------------------------


def rig_scores(
    positions: np.ndarray,
    parents: np.ndarray,
    joints: np.ndarray,
    true_parents: np.ndarray | None,
    points: np.ndarray,
) -> dict[str, float]:
    """Joint distance, the CD family, bone-length variation and TED of one rig's joints
    (T, J, 3) with tree `parents` (J,) against the true joints (T, J', 3)."""
    kept = np.ones(len(parents), bool)
    ones = np.ones((*positions.shape[:2], 1), np.float32)
    out = {
        "joint_distance": float(metrics.joint_distance(positions, joints, kept)),
        "bone_length_variation": float(
            metrics.bone_length_variation(
                np.concatenate([positions, ones], axis=-1), parents, kept=kept
            )
        ),
    }
    chamfers = metrics.skeleton_chamfers(positions, parents, joints, true_parents, points)
    out |= {key: float(np.mean(np.asarray(value))) for key, value in chamfers.items()}
    if true_parents is not None:
        out["tree_edit_distance"] = metrics.tree_edit_distance(parents, true_parents)
    return out


def picture(name, keypoints, points, joints, skeleton, arrays) -> dict[str, Any]:
    """`PICTURE_FRAMES` evenly spaced frames of one sequence for the figure: a fixed sample of
    its points, the true joints, the unrefined and the refined joints, both trees."""
    rig = unrefined_rig(name, keypoints, skeleton, 1.0)
    frames = np.unique(np.linspace(0, len(points) - 1, PICTURE_FRAMES).round().astype(int))
    sample = point_subset(points.shape[1], PICTURE_POINTS)

    def rounded(x: np.ndarray) -> list:
        return np.round(np.asarray(x, np.float64), 3).tolist()

    return {
        "sequence": name,
        "frames": frames.tolist(),
        "points": rounded(points[frames][:, sample]),
        "joints": rounded(joints[frames]),
        "unrefined": rounded(rig.positions[frames]),
        "refined": rounded(arrays["positions"][frames]),
        "parents": np.asarray(rig.parents).tolist(),
    }


def timing_case(keypoints: np.ndarray, points: np.ndarray, frames: int, count: int):
    """The timing sequence: `frames` frames of a sequence played back and forth, `count` of its
    points (the same indices in every frame; drawn with replacement when it has fewer)."""
    cycle = np.concatenate([np.arange(len(points)), np.arange(len(points) - 2, 0, -1)])
    index = cycle[np.arange(frames) % len(cycle)] if len(cycle) else np.zeros(frames, int)
    rng = np.random.default_rng(0)
    chosen = rng.choice(points.shape[1], count, replace=points.shape[1] < count)
    return keypoints[index], points[index][:, chosen]


def score_run(
    run: Path, settings: RefineSettings, timing: tuple[int, int], stamp: dict[str, Any]
) -> dict[str, Any]:
    """The row of one phase-1 run (module docstring)."""
    cfg = run_folder.load_config(run, SkelTrainConfig)
    skeleton = run_folder.pruned_skeleton(run)
    if skeleton is None:
        raise SystemExit(f"{run} has no skeleton.json; run `nmjax extract-skeleton --run {run}`")
    truth = read_meta(cfg.data.name, cfg.data.root).get("parents")
    true_parents = None if truth is None else np.asarray(truth, np.int64)
    names = sorted(run_folder.load_trajectories(run, "test"))
    joints_of = _sequence_joints(cfg, names)
    per_sequence, shown, first = {}, None, None
    for name, keypoints, points, scale in sequence_frames(run, "test", names):
        joints = joints_of[name]
        if joints is None:
            raise SystemExit(f"{name} of {cfg.data.name} has no true joints to score against")
        arrays, errors = refine_sequence(
            keypoints, points, skeleton, scale, settings, progress=True, name=name
        )
        rig = unrefined_rig(name, keypoints, skeleton, 1.0)
        unrefined = rig_scores(rig.positions, rig.parents, joints, true_parents, points)
        refined = rig_scores(arrays["positions"], arrays["parents"], joints, true_parents, points)
        unrefined |= {"rig_fit_cd": errors["fit_before"]}
        unrefined |= {"rig_fit_cd_capture": errors["fit_before_capture"]}
        refined |= {"rig_fit_cd": errors["fit_after"]}
        refined |= {"rig_fit_cd_capture": errors["fit_after_capture"], "seconds": errors["seconds"]}
        per_sequence[name] = {"frames": len(points), "unrefined": unrefined, "refined": refined}
        if shown is None:
            shown = picture(name, keypoints, points, joints, skeleton, arrays)
            first = (keypoints, points, scale)
        print(
            f"  {name}: joint distance {unrefined['joint_distance']:.3f} -> "
            f"{refined['joint_distance']:.3f}, fit x1e4 {errors['fit_before']:.1f} -> "
            f"{errors['fit_after']:.1f} ({errors['seconds']:.0f} s)",
            flush=True,
        )
    scores = {
        method: {
            key: float(np.mean(values))
            for key in MEASURES
            if (values := [s[method][key] for s in per_sequence.values() if key in s[method]])
        }
        for method in ("unrefined", "refined")
    }
    for method in scores:  # one tree a run: its distance an integer
        if "tree_edit_distance" in scores[method]:
            scores[method]["tree_edit_distance"] = int(scores[method]["tree_edit_distance"])
    keypoints, points = timing_case(first[0], first[1], *timing)
    tic = time.perf_counter()
    refine_sequence(keypoints, points, skeleton, first[2], settings, progress=True, name="timing")
    seconds = time.perf_counter() - tic
    row = {
        "body": cfg.data.name,
        "seed": cfg.seed,
        "run": str(run),
        "settings": dataclasses.asdict(settings),
        "scores": scores,
        "per_sequence": per_sequence,
        "timing": {
            "frames": timing[0],
            "points": timing[1],
            "seconds": seconds,
            "cores": len(os.sched_getaffinity(0)),
        },
        "picture": shown,
        "config": json.loads((run / run_folder.CONFIG_FILE).read_text()),
        "provenance": stamp,
    }
    row["targets"] = targets_of(row)
    return row


def _sequence_joints(cfg: SkelTrainConfig, names: list[str]) -> dict[str, np.ndarray | None]:
    """{name: (T, J, 3) true joints in the keypoints' cube, or None} of the test sequences."""
    from nmjax.data.datasets import load_sequences
    from nmjax.train.trained import sequence_points

    sequences = {s.name: s for s in load_sequences(cfg.data.name, "test", cfg.data.root)}
    return {n: sequence_points(sequences[n], cfg.data.sample_rate)[1] for n in names}


def targets_of(row: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """{target: {"unrefined", "refined", "met" (None: not measured), "ratio"}} of a row."""
    out = {}
    for key, (_, test) in TARGETS.items():
        if key == "timing_seconds":
            timing = row["timing"]
            measured = (timing["frames"], timing["points"]) == (TIMING_FRAMES, TIMING_POINTS)
            value = timing["seconds"]
            out[key] = {
                "unrefined": None,
                "refined": value,
                "met": bool(test(None, value)) if measured else None,
                "ratio": value / TIMING_SECONDS,
            }
            continue
        u, r = row["scores"]["unrefined"].get(key), row["scores"]["refined"].get(key)
        known = u is not None and r is not None and np.isfinite(u) and np.isfinite(r)
        out[key] = {
            "unrefined": u,
            "refined": r,
            "met": bool(test(u, r)) if known else None,
            "ratio": r / u if known and u else None,
        }
    return out


# --- rendering ----------------------------------------------------------------------------------


def _cell(value: Any, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.2e}" if 0 < abs(value) < 1e-3 else f"{value:.{digits}f}"
    return str(value)


def _verdict(target: dict[str, Any]) -> str:
    if target["met"] is None:
        return "not measured"
    ratio = "" if target["ratio"] is None else f" (refined / unrefined {target['ratio']:.2f})"
    return ("met" if target["met"] else "NOT met") + ratio


def markdown(body: str, stored: list[dict[str, Any]]) -> str:
    """The body's table: a block per row (seed), its targets, the definitions."""
    lines = [
        f"# The articulated refinement on {body}: refined against unrefined",
        "",
        "Each block is one phase-1 run scored on its test sequences (`experiments/refine_bench.py`"
        "): the rig `nmjax export` makes of the keypoints (unrefined) and the one `nmjax refine` "
        "fits from it (refined), on the same frames. Means over the test sequences.",
        "",
    ]
    if not stored:
        lines += ["No row yet.", ""]
    for row in sorted(stored, key=lambda r: (r["seed"], r["run"])):
        u, r = row["scores"]["unrefined"], row["scores"]["refined"]
        timing = row["timing"]
        lines += [
            f"## seed {row['seed']}: `{row['run']}` "
            f"({provenance.describe_commit(row['provenance'])})",
            "",
            f"{len(row['per_sequence'])} test sequence(s), {row['settings']['iterations']} "
            f"iterations, {row['settings']['surface_points']} surface / "
            f"{row['settings']['target_points']} target points.",
            "",
            "| measure | unrefined | refined | target |",
            "|---|---|---|---|",
        ]
        for key in SCORE_KEYS:
            target = row["targets"].get(key)
            verdict = "" if target is None else f"{TARGETS[key][0]}: {_verdict(target)}"
            lines.append(f"| {key} | {_cell(u.get(key))} | {_cell(r.get(key))} | {verdict} |")
        lines.append(f"| seconds per sequence | - | {_cell(r.get('seconds'), 1)} | |")
        lines.append(
            f"| seconds, {timing['frames']} frames x {timing['points']} points on "
            f"{timing['cores']} cores | - | {timing['seconds']:.1f} | "
            f"{TARGETS['timing_seconds'][0]}: {_verdict(row['targets']['timing_seconds'])} |"
        )
        lines.append("")
    lines += ["## Targets", ""]
    lines += [f"- **{k}**: {desc}" for k, (desc, _) in TARGETS.items()]
    lines += ["", "## Definitions", ""]
    lines += [f"- **{k}**: {v}" for k, v in METRICS.items()]
    return "\n".join(lines) + "\n"


def figure(body: str, stored: list[dict[str, Any]], path: Path, stamp) -> None:
    """Unrefined and refined skeletons over the same frames: a row pair per seed, a column per
    frame, the true joints in green."""
    stored = sorted(stored, key=lambda r: (r["seed"], r["run"]))
    cols = max([len(r["picture"]["frames"]) for r in stored] or [1])
    fig = plt.figure(figsize=(2.8 * cols, 2.9 * 2 * max(len(stored), 1)))
    for i, row in enumerate(stored):
        pic = row["picture"]
        keep = np.ones(len(pic["parents"]), bool)
        for m, method in enumerate(("unrefined", "refined")):
            for j, t in enumerate(pic["frames"]):
                ax = fig.add_subplot(
                    2 * len(stored), cols, (2 * i + m) * cols + j + 1, projection="3d"
                )
                draw_pruned_tree(
                    ax,
                    np.asarray(pic[method][j]),
                    pic["parents"],
                    keep,
                    np.asarray(pic["points"][j]),
                    title=f"seed {row['seed']} {method}\n{pic['sequence']} frame {t}",
                )
                ax.scatter(*np.asarray(pic["joints"][j]).T, s=6, c="tab:green", depthshade=False)
    save_figure(
        fig, path, title=f"{body}: unrefined and refined skeletons (true joints green)", dpi=80
    )
    provenance.stamp_png(path, stamp)


def render(body: str, store: rows.RowStore, out: Path, stamp) -> None:
    stored = store.read()
    provenance.write_markdown(out / f"refine_{body}.md", markdown(body, stored), stamp)
    figure(body, stored, out / f"refine_{body}.png", stamp)


# --- the plan -----------------------------------------------------------------------------------


def default_runs(bodies: list[str], seeds: list[int]) -> list[Path]:
    """The `cpu`-preset phase-1 runs of `paper_phase1.py` (trained where missing)."""
    import paper_phase1

    runs = []
    for seed in seeds:
        for body in bodies:
            key = paper_phase1.RowKey(body, seed, "preset")
            run, minutes = paper_phase1.train(key, paper_phase1.row_config(key))
            if minutes is not None:
                print(f"--- trained {run} ({minutes:.0f} min)", flush=True)
            runs.append(run)
    return runs


def store_of(body: str, out: Path) -> rows.RowStore:
    return rows.RowStore(
        out / f"refine_{body}.json",
        METRICS,
        SINCE,
        key=("body", "seed", "run"),
        config_class=SkelTrainConfig,
        repo=Path(__file__).parent,
    )


def main(argv: list[str] | None = None) -> None:
    defaults = RefineSettings()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", nargs="+", type=Path, default=None, help="phase-1 runs to score")
    parser.add_argument("--data", nargs="+", default=list(BODIES), choices=BODIES)
    parser.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    parser.add_argument("--iters", type=int, default=defaults.iterations)
    parser.add_argument("--surface-points", type=int, default=defaults.surface_points)
    parser.add_argument("--target-points", type=int, default=defaults.target_points)
    parser.add_argument("--timing-frames", type=int, default=TIMING_FRAMES, help="smoke tests")
    parser.add_argument("--timing-points", type=int, default=TIMING_POINTS, help="smoke tests")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--allow-dirty", action="store_true", help="run with uncommitted changes")
    args = parser.parse_args(argv)
    settings = dataclasses.replace(
        defaults,
        iterations=args.iters,
        surface_points=args.surface_points,
        target_points=args.target_points,
    )
    timing = (args.timing_frames, args.timing_points)
    rows.refuse_dirty("refine_bench.py", args.allow_dirty)
    stamp = provenance.stamp(METRICS)
    runs = args.run if args.run is not None else default_runs(args.data, args.seeds)
    bodies = set()
    for run in runs:
        cfg = run_folder.load_config(run, SkelTrainConfig)
        body = cfg.data.name
        store = store_of(body, args.out)
        stored = store.read()

        def same(row: dict[str, Any]) -> bool:
            return (
                row["settings"] == dataclasses.asdict(settings)
                and (
                    row["timing"]["frames"],
                    row["timing"]["points"],
                )
                == timing
            )

        if store.keeps(store.find(stored, body=body, seed=cfg.seed, run=str(run)), cfg, same):
            print(f"--- {run}: row kept", flush=True)
        else:
            print(f"--- {run}: refining its test sequences", flush=True)
            row = score_run(run, settings, timing, stamp)
            store.write(store.put(stored, row), stamp)
            missed = [k for k, t in row["targets"].items() if t["met"] is False]
            print(f"--- {run}: targets not met: {', '.join(missed) or 'none'}", flush=True)
        bodies.add(body)
    for body in sorted(bodies):
        render(body, store_of(body, args.out), args.out, stamp)
        print(f"wrote {args.out / f'refine_{body}'}.{{json,md,png}}")


if __name__ == "__main__":
    main()
