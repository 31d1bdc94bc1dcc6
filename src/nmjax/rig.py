"""`nmjax rig`: your own capture to a skinned, animated rig in one command.

    nmjax rig --from RAW --out RIG.glb [--mesh REST.obj] [--seq NAME] [--preset cpu]
              [--steps N | --minutes M] [--work DIR] [--up z] [--fps 30] [--units m]

`make_rig` runs the stages of docs/architecture.md §3 on a capture `nmjax prepare-data --from
RAW` reads (a folder of mesh or point frames, one such folder per sequence, or one (T, N, 3)
array per sequence):

1. prepare: RAW as the generic `capture` set into WORK/data (`prepare.prepare_capture`);
2. phase 1: the detector and affinity trained on it into the run folder WORK/skel
   (`skel.train_skeleton`, the `capture` spec at `--preset`), ending with Algorithm 1's
   skeleton (`trained.complete_phase1`);
3. motion: the trained detector's keypoints of every frame of one sequence of the capture
   (`--seq`, default the first), the whole sequence normalised with one box as
   `trained.export_keypoints` does, then mapped out of the cube into the capture's own frame
   and units by the inverse of that box (`normalize.undo_box`); kept in WORK/motion.npz;
4. skin: the rig `nmjax export` builds from a phase-1 run (`evaluate.field_scores.crop_rig`:
   the kept nodes as joints, frame 0 as the rest pose, swing rotations from the bones) with
   Algorithm 2's weights of the rest surface: `--mesh`, else frame 0 of a mesh capture, else
   frame 0's points (written as a glTF POINTS primitive). The rest surface is bound in frame
   0's pose, so a `--mesh` must be in that pose and place, in the capture's units;
5. write: RIG.glb (the skinned surface, the skeleton and an animation keyed at every frame),
   RIG.bvh and RIG.png beside it, the capture's up axis turned to glTF's +Y
   (`export.rig.file_axes`), lengths in the capture's units. The three files are written into
   a temporary folder beside RIG.glb and moved into place together: a failure leaves none.

The rig's fit error is the evaluation's `rig fit` (`field_scores.crop_fit_error`,
`metrics.rig_fit_error`): the capture's frame-0 points skinned by the rig against each frame's
points, a Chamfer distance of squared distances, x1e4 in the cube and in the capture's units
(squared).

Every refusal `nmjax prepare-data` makes is made before any training, and every check of the
command itself (the outputs, the budget, the sequence, the mesh, the work folder) before
anything is written (`check`). The work folder (`--work`, default RIG-work beside RIG.glb)
records the settings its stages were made with (rig.json); a rerun of the same command reuses
the prepared set, resumes or reuses the phase-1 run and reuses the motion.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from nmjax import atomic, run_folder
from nmjax.config import SkelTrainConfig, skel_preset, with_steps
from nmjax.config_io import apply_overrides, replace_fields
from nmjax.data.layout import CAPTURE, capture_meta
from nmjax.data.prepare import DEFAULT_POINTS
from nmjax.export.rig import Rig, file_axes, transform

# The phase-1 budget when neither --steps nor --minutes is given. None trains the capture
# preset's own steps (the `capture` spec: 20,000 at --preset default, 2,200 at cpu, 20 at tiny).
# The phase-1 budget study (experiments/phase1_budget.py, how long until a skeleton is a
# skeleton) decides the number that replaces it.
DEFAULT_STEPS: int | None = None

SETTINGS_FILE = "rig.json"  # in the work folder: its settings and phase 1's record
DATA_DIR, SKEL_DIR, MOTION_FILE = "data", "skel", "motion.npz"
PICTURE_FRAMES = 4  # panels of RIG.png, spread evenly over the capture
PICTURE_POINTS = 2000  # points of each cloud drawn in a panel, at most
# Frames the fit error compares at most, spread evenly with frame 0 first: one Chamfer of two
# 4,096-point frames (`field_scores.FIT_POINTS`) is about 0.2 s on 2 cores.
FIT_FRAMES = 40
# The settings a work folder's stages depend on: another value is another rig. The budget,
# the sequence and the mesh are not among them (a rerun may train on, or skin another mesh).
STAGE_SETTINGS = ("source", "points", "seed", "up", "fps", "units", "preset", "overrides")


@dataclasses.dataclass(frozen=True)
class RigOptions:
    """What `nmjax rig` is asked (the command's options; None: not given)."""

    source: Path
    out: Path
    mesh: Path | None = None
    seq: str | None = None
    preset: str = "default"
    steps: int | None = None
    minutes: float | None = None
    work: Path | None = None
    points: int = DEFAULT_POINTS
    seed: int = 0
    up: str | None = None
    fps: float | None = None
    units: str | None = None
    overrides: tuple[str, ...] = ()
    overwrite: bool = False
    progress: bool = True

    @property
    def outputs(self) -> tuple[Path, Path, Path]:
        """RIG.glb and, beside it, RIG.bvh and RIG.png."""
        out = Path(self.out)
        return out, out.with_suffix(".bvh"), out.with_suffix(".png")

    @property
    def work_dir(self) -> Path:
        out = Path(self.out)
        return Path(self.work) if self.work is not None else out.with_name(f"{out.stem}-work")


@dataclasses.dataclass(frozen=True)
class Surface:
    """The rest surface to skin, in the capture's units: vertices (V, 3), faces (F, 3) or None
    (points), and where it came from."""

    vertices: np.ndarray
    faces: np.ndarray | None
    origin: str


@dataclasses.dataclass(frozen=True)
class Plan:
    """Everything `check` found: the sequence to animate, the rest surface, the capture's
    meta.json entries, the settings rig.json records and the phase-1 budget ("steps N", the
    steps a new run trains, or "minutes M")."""

    seq: str
    surface: Surface
    meta: dict[str, Any]
    settings: dict[str, Any]
    budget: str


@dataclasses.dataclass(frozen=True)
class RigResult:
    """What `make_rig` made.

    Attributes:
      rig: the rig as written: glTF's axes (+Y up), the capture's units.
      options: what was asked; plan: what `check` found.
      skel_run: the phase-1 run folder; num_keypoints: its detector's K; steps: the run's
        steps; phase1: "trained", "resumed from step N" or "reused".
      fit: {"cd": x1e4 in the cube, "cd_capture": the capture's units, squared, "frames": n}.
      seconds: wall time of each stage ("prepare", "phase1", "motion", "skin", "fit", "write",
        "picture") and "total".
      reused: the stages taken from the work folder.
    """

    rig: Rig
    options: RigOptions
    plan: Plan
    skel_run: Path
    num_keypoints: int
    steps: int
    phase1: str
    fit: dict[str, float]
    seconds: dict[str, float]
    reused: tuple[str, ...]

    def summary(self) -> str:
        """The lines `nmjax rig` ends with."""
        glb, bvh, png = self.options.outputs
        rig, plan = self.rig, self.plan
        units = plan.meta["units"]
        kind = "mesh" if rig.faces is not None else "points"
        surface = f"{len(rig.vertices):,} vertices" + (
            f", {len(rig.faces):,} faces" if rig.faces is not None else ""
        )
        stages = ", ".join(
            f"{name} {self.seconds[name]:.1f} s" + (" (reused)" if name in self.reused else "")
            for name in ("prepare", "phase1", "motion", "skin", "fit", "write", "picture")
        )
        return "\n".join(
            [
                f"nmjax rig: {glb} from {self.options.source} (sequence {plan.seq}) in "
                f"{self.seconds['total']:.1f} s",
                f"  joints: {len(rig.joints)} kept of the {self.num_keypoints} keypoints "
                f"(phase 1 {self.phase1}, {self.steps:,} steps, {self.skel_run})",
                f"  frames: {rig.num_frames} at {rig.frame_rate:g} fps, every frame of the "
                f"capture; +Y up (the capture's {plan.meta['up']}), lengths in {units}",
                f"  skinned {kind}: {surface} ({plan.surface.origin})",
                f"  fit error: {self.fit['cd']:.2f} x1e-4 in the normalised cube, "
                f"{self.fit['cd_capture']:.3g} {units}^2 in the capture's units (Chamfer of "
                f"squared distances over {self.fit['frames']} frames)",
                f"  files: {glb}, {bvh}, {png}; work folder {self.options.work_dir} (a rerun "
                "of this command reuses it)",
                f"  time: {stages}",
            ]
        )


# --- checks: everything refused before anything is written -------------------------------------


def read_rest_mesh(path: Path) -> Surface:
    """The `--mesh` to skin, read as `prepare-data` reads a frame.

    Raises:
      FileNotFoundError, ValueError: naming the file (missing, unreadable, NaN / inf, no faces).
    """
    from nmjax.data.meshes import read_frame, require_finite

    if not path.is_file():
        raise FileNotFoundError(
            f"--mesh {path} does not exist; give the mesh to skin (.obj, .ply, .off), or leave "
            "--mesh out to skin frame 0 of the capture"
        )
    vertices, faces = read_frame(path, "give an .obj, .ply or .off mesh with faces")
    require_finite(vertices, f"--mesh {path}")
    if len(faces) == 0:
        raise ValueError(
            f"--mesh {path} has no faces: it is a point cloud of {len(vertices)} points; give a "
            "mesh with triangles, or leave --mesh out (a point capture is skinned as its "
            "frame-0 points)"
        )
    return Surface(vertices, faces, f"--mesh {path}")


def frame0_surface(found: list[Path] | Path) -> Surface:
    """Frame 0 of a sequence `prepare.find_sequences` listed: its mesh, or its points.

    Raises:
      ValueError: naming the file (unreadable, NaN / inf).
    """
    from nmjax.data.meshes import read_frame, read_point_array, require_finite

    if isinstance(found, Path):  # one (T, N, 3) array
        return Surface(read_point_array(found, 1)[0], None, f"frame 0 of {found}")
    vertices, faces = read_frame(found[0])
    require_finite(vertices, str(found[0]))
    return Surface(vertices, faces if len(faces) else None, f"frame 0 of the capture, {found[0]}")


def phase1_config(options: RigOptions, root: Path | None = None) -> SkelTrainConfig:
    """The phase-1 configuration of a new run: the `capture` spec at `options.preset` (with the
    up axis and frame rate of `root`'s meta.json when `root` is prepared), `--set` applied,
    `--steps` (or `DEFAULT_STEPS`) as the run's length, into WORK/skel."""
    from nmjax.data.layout import training_config
    from nmjax.train.skel import check_config

    if root is None:
        cfg = skel_preset(CAPTURE, options.preset)
    else:
        cfg = training_config(CAPTURE, root, options.preset)
    cfg = apply_overrides(cfg, options.overrides)
    steps = DEFAULT_STEPS if options.steps is None else options.steps
    if steps is not None:
        cfg = with_steps(cfg, steps)
    cfg = dataclasses.replace(cfg, run=str(options.work_dir / SKEL_DIR))
    check_config(cfg)
    return cfg


def read_settings(work: Path) -> dict[str, Any]:
    """The work folder's rig.json ({} when it has none).

    Raises:
      ValueError: a folder that holds other files but no rig.json, or a damaged rig.json.
    """
    path = work / SETTINGS_FILE
    if not path.is_file():
        if work.exists() and (not work.is_dir() or any(work.iterdir())):
            raise ValueError(
                f"--work {work} holds files but no {SETTINGS_FILE}: it is no work folder of "
                "`nmjax rig`; give another --work (an empty or new folder)"
            )
        return {}
    try:
        stored = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path} is not valid JSON ({err}); delete {work} to start over") from err
    if not isinstance(stored, dict) or not isinstance(stored.get("settings"), dict):
        raise ValueError(f"{path} holds no `settings`; delete {work} to start over")
    return stored


def check(options: RigOptions) -> Plan:
    """Every refusal of `nmjax rig` that needs no training, before anything is written.

    Raises:
      FileExistsError: an output exists and not `options.overwrite`.
      FileNotFoundError, ValueError: one line naming the bad input and the fix.
    """
    from nmjax.data import prepare

    glb = Path(options.out)
    if glb.suffix.lower() != ".glb":
        raise ValueError(
            f"--out {glb}: give a file ending in .glb (the rig; RIG.bvh and RIG.png are "
            "written beside it)"
        )
    for path in options.outputs:
        if path.is_dir():
            raise IsADirectoryError(f"{path} is a folder; give --out a file name ending in .glb")
        if path.exists() and not options.overwrite:
            raise FileExistsError(f"{path} exists; pass --overwrite to replace it")
    if options.steps is not None and options.minutes is not None:
        raise ValueError("give --steps or --minutes, not both")
    if options.steps is not None and options.steps < 1:
        raise ValueError(f"--steps must be >= 1, got {options.steps}")
    if options.minutes is not None and not options.minutes > 0:
        raise ValueError(f"--minutes must be > 0, got {options.minutes}")
    if options.points < 1:
        raise ValueError(f"--points must be >= 1, got {options.points}")
    meta = capture_meta(options.up, options.fps, options.units)
    cfg = phase1_config(options)  # refuses a --preset / --set that cannot train
    budget = (
        f"steps {cfg.loop.steps}" if options.minutes is None else f"minutes {options.minutes:g}"
    )
    sequences = prepare.find_sequences(Path(options.source))
    seq = next(iter(sequences)) if options.seq is None else options.seq
    if seq not in sequences:
        raise ValueError(
            f"--seq {seq!r} is not a sequence of {options.source}; it holds "
            f"{', '.join(list(sequences)[:8])}"
        )
    if options.mesh is not None:
        surface = read_rest_mesh(Path(options.mesh))
    else:
        surface = frame0_surface(sequences[seq])
    settings = {
        "source": str(Path(options.source).resolve()),
        "points": options.points,
        "seed": options.seed,
        **{k: meta[k] for k in ("up", "fps", "units")},
        "preset": options.preset,
        "overrides": list(options.overrides),
    }
    stored = read_settings(options.work_dir).get("settings")
    if stored is not None and any(stored.get(k) != settings[k] for k in STAGE_SETTINGS):
        changed = ", ".join(
            f"{k} (there: {stored.get(k)!r}, asked: {settings[k]!r})"
            for k in STAGE_SETTINGS
            if stored.get(k) != settings[k]
        )
        raise ValueError(
            f"--work {options.work_dir} holds the rig of other settings: {changed}; give "
            f"another --work, or delete {options.work_dir} to start over"
        )
    return Plan(seq, surface, meta, settings, budget)


# --- the stages ---------------------------------------------------------------------------------


def prepare_stage(options: RigOptions, plan: Plan) -> tuple[Path, bool]:
    """WORK/data, the capture prepared (`prepare.prepare_capture`); (the folder, reused)."""
    from nmjax.data import prepare

    root = options.work_dir / DATA_DIR
    if (root / "meta.json").is_file():
        return root, True
    prepare.prepare_capture(
        Path(options.source),
        root,
        up=plan.meta["up"],
        fps=plan.meta["fps"],
        units=plan.meta["units"],
        points=options.points,
        seed=options.seed,
    )
    return root, False


def phase1_stage(
    options: RigOptions, plan: Plan, root: Path, record: dict
) -> tuple[Path, int, str]:
    """The phase-1 run WORK/skel, trained, resumed or reused; (the run, its steps, what was
    done: "trained", "resumed from step N" or "reused").

    A run without a checkpoint starts anew (with `--minutes`, its steps fitted to the minutes:
    `bench.fit_to_minutes`). A run with checkpoints is reused when it finished the budget asked
    now (`record`, rig.json's "phase1"), else resumed: to `--steps` (or the preset's steps), or,
    with `--minutes`, to its own steps. Only the run's length may change on a resume.
    """
    from nmjax.train import skel

    run = options.work_dir / SKEL_DIR
    done = run_folder.checkpoint_steps(run)
    if not done:
        started = time.perf_counter()
        cfg = phase1_config(options, root)
        if options.minutes is not None:
            from nmjax import bench

            cfg, _ = bench.fit_to_minutes(cfg, options.minutes, started)
        summary = skel.train_skeleton(cfg, overwrite=True, progress=options.progress)
        return run, summary.step, "trained"
    finished = (
        record.get("budget") == plan.budget
        and record.get("step") == done[-1]
        and (run / run_folder.SKELETON_FILE).is_file()
        and all(run_folder.keypoints_file(run, s).is_file() for s in run_folder.SPLITS)
    )
    if finished:
        return run, done[-1], "reused"
    saved = run_folder.load_config(run, SkelTrainConfig)
    if options.minutes is not None:
        target = saved.loop.steps
    else:
        target = phase1_config(options, root).loop.steps
    cfg = replace_fields(saved, steps=target, run=str(run))
    cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, root=str(root)))
    summary = skel.train_skeleton(cfg, resume=True, progress=options.progress)
    return run, summary.step, f"resumed from step {summary.start_step:,}"


def detect_every_frame(detector: Any, cube: np.ndarray) -> np.ndarray:
    """(T, K, 4) keypoints of every frame of a normalised sequence (T, N, 3): consecutive windows
    of the detector's T_crop frames (the last padded with the last frame), as
    `trained.export_keypoints` cuts a whole sequence, voxelised a few windows at a time."""
    from nmjax.data.voxelize import voxelize
    from nmjax.train.trained import sequence_windows

    data = detector.cfg.data
    chunk = data.frames * detector.batch_size * 4  # frames voxelised at once (whole windows)
    parts = []
    for start in range(0, len(cube), chunk):
        voxels = voxelize(cube[start : start + chunk], data.grid)
        keypoints = detector.keypoints(sequence_windows(voxels, data.frames))
        parts.append(keypoints.reshape(-1, *keypoints.shape[2:])[: len(voxels)])
    return np.concatenate(parts).astype(np.float32)


def motion_stage(
    run: Path, root: Path, seq: str, work: Path, key: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    """The detector's keypoints of every frame of sequence `seq`, in the cube of one box over
    the whole sequence (kept in WORK/motion.npz under `key`, the phase-1 run it came from).

    Returns:
      (points (T, N, 3) of the capture in the cube, keypoints (T, K, 4) in the cube, box minimum
      (3,), box scale (1,): p' = scale (p - bmin) - 1; whether the keypoints were reused).
    """
    from nmjax.data.datasets import whole_sequence
    from nmjax.data.normalize import apply_box, normalization_box
    from nmjax.train import trained

    points = whole_sequence(CAPTURE, seq, root)
    bmin, scale = normalization_box(points)
    bmin, scale = bmin[0, 0], scale[0, 0]
    cube = apply_box(points, bmin, scale).astype(np.float32)
    path = work / MOTION_FILE
    if path.is_file():
        with np.load(path) as z:
            if str(z["key"]) == key and z["keypoints"].shape[0] == len(cube):
                return cube, np.asarray(z["keypoints"]), bmin, scale, True
    keypoints = detect_every_frame(trained.Detector.load(run), cube)
    atomic.save_npz(path, keypoints=keypoints, key=np.asarray(key))
    return cube, keypoints, bmin, scale, False


def evenly(count: int, most: int) -> np.ndarray:
    """Up to `most` frame indices spread evenly over `count` frames, frame 0 first."""
    return np.unique(np.linspace(0, count - 1, min(count, most)).round().astype(int))


def some(count: int, most: int) -> np.ndarray:
    """Up to `most` of `count` point indices, drawn once with a fixed seed, in order."""
    if count <= most:
        return np.arange(count)
    return np.sort(np.random.default_rng(0).choice(count, most, replace=False))


def write_files(
    options: RigOptions, rig: Rig, picture: dict[str, Any], seconds: dict[str, float]
) -> None:
    """RIG.glb, RIG.bvh and RIG.png, written into a temporary folder beside RIG.glb and moved
    into place together, so that a failure leaves none of them."""
    from nmjax import viz
    from nmjax.export import bvh, gltf

    outputs = options.outputs
    outputs[0].parent.mkdir(parents=True, exist_ok=True)
    temporary = Path(tempfile.mkdtemp(prefix=".nmjax-rig-", dir=outputs[0].parent))
    try:
        begin = time.perf_counter()
        gltf.write(rig, temporary / outputs[0].name)
        bvh.write(rig, temporary / outputs[1].name)
        seconds["write"] = time.perf_counter() - begin
        begin = time.perf_counter()
        viz.draw_rig(temporary / outputs[2].name, **picture)
        seconds["picture"] = time.perf_counter() - begin
        for path in outputs:
            os.replace(temporary / path.name, path)
    finally:
        shutil.rmtree(temporary, ignore_errors=True)


def make_rig(options: RigOptions) -> RigResult:
    """The stages of the module docstring; the work folder is `options.work_dir`.

    A work folder this call creates is removed again when preparing the capture fails (a bad
    frame): nothing is left behind before training starts.

    Raises:
      FileExistsError, FileNotFoundError, ValueError: one line naming the bad input and the fix.
      NonFiniteLossError: phase 1's loss became NaN / inf.
    """
    from nmjax.data.datasets import load_sequences
    from nmjax.data.normalize import apply_box, undo_box
    from nmjax.evaluate.field_scores import crop_fit_error, crop_rig, skinned_surface

    begin = time.perf_counter()
    plan = check(options)
    work = options.work_dir
    created = next(
        (p for p in (*reversed(work.absolute().parents), work.absolute()) if not p.exists()), None
    )  # the outermost folder this call makes
    stored = read_settings(work)
    seconds: dict[str, float] = {}
    reused: list[str] = []

    def lap(stage: str, since: float) -> float:
        seconds[stage] = time.perf_counter() - since
        return time.perf_counter()

    tic = time.perf_counter()
    try:
        work.mkdir(parents=True, exist_ok=True)
        atomic.write_json(work / SETTINGS_FILE, {**stored, "settings": plan.settings})
        root, was_there = prepare_stage(options, plan)
        for split in run_folder.SPLITS:  # what the trainer refuses before its first step
            load_sequences(CAPTURE, split, root)
    except BaseException:
        if created is not None:  # nothing is left of a capture refused before training
            shutil.rmtree(created, ignore_errors=True)
        raise
    reused += ["prepare"] if was_there else []
    tic = lap("prepare", tic)

    run, steps, phase1 = phase1_stage(options, plan, root, stored.get("phase1", {}))
    record = {"budget": plan.budget, "step": run_folder.checkpoint_steps(run)[-1]}
    atomic.write_json(work / SETTINGS_FILE, {"settings": plan.settings, "phase1": record})
    reused += ["phase1"] if phase1 == "reused" else []
    tic = lap("phase1", tic)

    key = json.dumps({"seq": plan.seq, **record}, sort_keys=True)
    cube, keypoints, bmin, scale, was_there = motion_stage(run, root, plan.seq, work, key)
    reused += ["motion"] if was_there else []
    tic = lap("motion", tic)

    fps, up_axis = run_folder.motion_format(run)
    skeleton = run_folder.pruned_skeleton(run)
    if skeleton is None:  # complete_phase1 said why
        raise FileNotFoundError(
            f"{run} holds no {run_folder.SKELETON_FILE}; run `nmjax extract-skeleton --run "
            f"{run}`, then this command again"
        )
    surface = plan.surface
    rest = apply_box(surface.vertices, bmin, scale)
    in_cube, weights = crop_rig(keypoints, rest, skeleton, fps)
    rig = dataclasses.replace(
        in_cube,
        name=plan.seq,
        positions=undo_box(in_cube.positions, bmin, scale),
        rest_positions=undo_box(in_cube.rest_positions, bmin, scale),
        vertices=np.asarray(surface.vertices, np.float64),
        faces=surface.faces,
        weights=weights,
    )
    tic = lap("skin", tic)

    frames = evenly(len(cube), FIT_FRAMES)
    fit = crop_fit_error(keypoints[frames], cube[frames], float(scale[0]), skeleton, fps)
    fit = {**fit, "frames": len(frames)}
    seconds["fit"] = time.perf_counter() - tic

    axes = file_axes(up_axis)
    shown = evenly(len(cube), PICTURE_FRAMES)
    posed = dataclasses.replace(rig, positions=rig.positions[shown], rotations=rig.rotations[shown])
    subset = some(len(rig.vertices), PICTURE_POINTS)
    skinned = skinned_surface(posed, rig.vertices[subset], weights[subset])
    captured = undo_box(cube[shown][:, some(cube.shape[1], PICTURE_POINTS)], bmin, scale)
    picture = {
        "frames": shown,
        "captured": captured @ axes.T,
        "surface": skinned @ axes.T,
        "joints": posed.positions @ axes.T,
        "parents": rig.parents,
        "title": f"{Path(options.out).name}: {len(rig.joints)} joints, {len(cube)} frames",
    }
    rig = transform(rig, axes)
    write_files(options, rig, picture, seconds)
    seconds["total"] = time.perf_counter() - begin
    return RigResult(
        rig=rig,
        options=options,
        plan=plan,
        skel_run=run,
        num_keypoints=int(keypoints.shape[1]),
        steps=steps,
        phase1=phase1,
        fit=fit,
        seconds=seconds,
        reused=tuple(reused),
    )
