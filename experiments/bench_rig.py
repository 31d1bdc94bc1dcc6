"""What `nmjax rig` adds beyond training, timed, beside the minutes phase 1 trains.

    JAX_PLATFORMS=cpu .venv/bin/python experiments/bench_rig.py [--preset cpu] [--frames 40]
        [--points 8000] [--vertices 40000] [--out experiments/results/bench_rig.json]

The issue's case: a 40-frame capture of 8,000 points a frame (the synthetic arm in motion, one
vertices-only .ply a frame) rigged with a 40,000-vertex mesh of frame 0's surface (`--mesh`),
the target at most 30 s on 2 cores for everything but training:

1. `nmjax.rig.make_rig` on it at `--preset` with `--train-steps` phase-1 steps (default 2: the
   network is the preset's, so detecting and skinning cost what they cost after a real run,
   while training, not timed here, stays short); its stages' wall times: prepare, motion (the
   detector over every frame), skin (Algorithm 2), fit (the fit error), write (.glb and .bvh),
   picture (RIG.png);
2. the skeleton (Algorithm 1 on the run's affinity, with its drawing, `extract_run_skeleton`),
   which the phase-1 stage runs last, timed on its own on the same run;
3. phase 1 itself, derived: the train step of the preset timed on the prepared capture
   (`nmjax.bench.bench_skel`: median compute + load a step, and the compile), times the preset's
   steps (`nmjax.rig.DEFAULT_STEPS`, else the `capture` spec's).

Run it on a quiet machine. Prints a table; `--out` writes the rows as JSON with the provenance
stamp (`nmjax.provenance`).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh

from nmjax import provenance
from nmjax.data import synthetic
from nmjax.data.bodies import get_body
from nmjax.data.layout import training_config

STAGES = ("prepare", "skeleton", "motion", "skin", "fit", "write", "picture")
METRICS = {
    "stage_s": "wall seconds of each stage of `nmjax rig` but training (the module docstring)",
    "beyond_training_s": "the sum of the stages",
    "step_s": "phase-1 train step at the preset on the capture: median compute + mean load",
    "training_min": "the preset's phase-1 steps x step_s, plus the step's compile, in minutes",
}


def rest_mesh(positions: np.ndarray, rotations: np.ndarray, vertices: int) -> trimesh.Trimesh:
    """The arm's surface in one pose (joint positions (J, 3), rotations (J, 3, 3)), its shared
    corners merged, subdivided (all faces, then a seeded share of them) until it has at least
    `vertices` vertices."""
    triangles, owner = synthetic.body_triangles(get_body("synth-arm"))
    world = np.einsum("fij,fcj->fci", rotations[owner], triangles) + positions[owner, None]
    mesh = trimesh.Trimesh(**trimesh.triangles.to_kwargs(world))
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    rng = np.random.default_rng(0)
    while len(v) < vertices:
        # A subdivided face adds about 1.5 vertices (its three edge midpoints, shared).
        count = min(len(f), max(int((vertices - len(v)) / 1.5), 1))
        v, f = trimesh.remesh.subdivide(v, f, np.sort(rng.choice(len(f), count, replace=False)))
    return trimesh.Trimesh(v, f, process=False)


def write_capture(folder: Path, frames: int, points: int, vertices: int) -> tuple[Path, Path]:
    """The capture (RAW, one .ply of `points` points a frame) and its rest mesh (.obj)."""
    body = get_body("synth-arm")
    rng = np.random.default_rng(0)
    angles, root = synthetic.sample_motion(body, frames, rng)
    positions, rotations = synthetic.pose(body, angles, root)
    clouds = synthetic.sample_body_surface(body, positions, rotations, points, rng)
    raw = folder / "reach"
    raw.mkdir(parents=True)
    for t, cloud in enumerate(clouds):
        trimesh.PointCloud(cloud).export(raw / f"frame_{t:03d}.ply")
    mesh = folder / "rest.obj"
    rest_mesh(positions[0], rotations[0], vertices).export(mesh)
    return raw, mesh


def bench(
    preset: str,
    frames: int,
    points: int,
    vertices: int,
    train_steps: int,
    step_steps: int,
    overrides: tuple[str, ...] = (),
) -> dict:
    """The rows of the module docstring; `overrides`: `--set` of the phase-1 configuration."""
    from nmjax import bench as step_bench
    from nmjax.config_io import apply_overrides, replace_fields
    from nmjax.rig import DEFAULT_STEPS, RigOptions, make_rig
    from nmjax.train import trained

    with tempfile.TemporaryDirectory() as tmp:
        raw, mesh = write_capture(Path(tmp), frames, points, vertices)
        options = RigOptions(
            source=raw,
            out=Path(tmp) / "out" / "rig.glb",
            mesh=mesh,
            preset=preset,
            steps=train_steps,
            overrides=overrides,
            progress=False,
        )
        result = make_rig(options)
        stages = {k: result.seconds[k] for k in STAGES if k != "skeleton"}
        tic = time.perf_counter()
        trained.extract_run_skeleton(result.skel_run)
        stages["skeleton"] = time.perf_counter() - tic
        cfg = training_config(root=options.work_dir / "data", preset=preset)
        cfg = apply_overrides(cfg, overrides)
        steps = cfg.loop.steps if DEFAULT_STEPS is None else DEFAULT_STEPS
        row = step_bench.bench_skel(replace_fields(cfg, steps=steps), preset, step_steps, 2)
        surface = len(result.rig.vertices)
    step_s = row["compute_s_median"] + row["load_s_per_step"]
    return {
        "preset": preset,
        "frames": frames,
        "points": points,
        "mesh_vertices": surface,
        "joints": len(result.rig.joints),
        "stage_s": {k: stages[k] for k in STAGES},
        "beyond_training_s": sum(stages.values()),
        "phase1_steps": steps,
        "step_s": step_s,
        "compile_s": row["compile_s"],
        "training_min": (steps * step_s + row["compile_s"]) / 60.0,
        "bench_row": row,
    }


def table(rows: dict) -> str:
    lines = [
        f"`nmjax rig --preset {rows['preset']}` on {rows['frames']} frames of "
        f"{rows['points']:,} points, skinning a {rows['mesh_vertices']:,}-vertex mesh "
        f"({rows['joints']} joints)",
        "",
        "| stage | seconds |",
        "|---|---|",
        *(f"| {k} | {v:.1f} |" for k, v in rows["stage_s"].items()),
        f"| **beyond training** | **{rows['beyond_training_s']:.1f}** (target <= 30) |",
        f"| phase 1 (derived): {rows['phase1_steps']:,} steps x {rows['step_s']:.3f} s + "
        f"{rows['compile_s']:.0f} s compile | {60 * rows['training_min']:.0f} "
        f"({rows['training_min']:.1f} min) |",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--points", type=int, default=8000)
    parser.add_argument("--vertices", type=int, default=40_000)
    parser.add_argument("--train-steps", type=int, default=2, help="phase-1 steps actually run")
    parser.add_argument("--step-steps", type=int, default=10, help="train steps timed")
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], help="phase-1 config field"
    )
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    stamp = provenance.stamp(METRICS)
    rows = bench(
        args.preset,
        args.frames,
        args.points,
        args.vertices,
        args.train_steps,
        args.step_steps,
        tuple(args.overrides),
    )
    print(table(rows))
    if args.out is not None:
        provenance.write_json(args.out, rows, stamp)
    return rows


if __name__ == "__main__":
    main()
