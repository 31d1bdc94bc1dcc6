"""`nmjax rig --from RAW --out RIG.glb` on captures written in the test (a synthetic arm as one
.obj mesh a frame, and as one vertices-only .ply a frame), at the tests' tiny phase-1 size: the
files it writes (their frames, axes and units, the mesh or points skinned), its work folder
reused and resumed, every bad input refused in one line with nothing left behind, and the .glb
and .bvh opened by headless Blender (`tests/blender_rig.py`), whose deformed mesh must be
nmjax's own skinned mesh.

The test checks the files, not the rig's quality: a few steps leave the detector untrained, its
keypoints in one spot, where every bone has length 0 and every rotation is the identity. So the
second run of each capture replaces the motion stage's keypoints (WORK/motion.npz) with the
arm's true joints, in the cube of that stage's box: a motion whose bones turn, on which the
writers and Blender's skinning are checked.
"""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pygltflib
import pytest
import trimesh
from captures import arm_meshes, arm_motion, arm_points, bad_capture, write_frames, write_meshes
from gltf_validator import validate
from programs import require_program

from nmjax import run_folder
from nmjax.cli import main as nmjax_main
from nmjax.config import SkelTrainConfig
from nmjax.data.datasets import whole_sequence
from nmjax.data.layout import CAPTURE
from nmjax.data.normalize import apply_box, normalization_box
from nmjax.evaluate.field_scores import skinned_surface
from nmjax.export import gltf
from nmjax.export.rig import file_axes
from nmjax.rig import MOTION_FILE, RigOptions, make_rig

FRAMES, FPS, POINTS = 24, 24.0, 400
# The tiny preset at the tests' G=8 size (tests/tiny_configs.py), K = 4 keypoints.
SMALL = (
    "data.grid=8",
    "model.grid=8",
    "data.frames=3",
    "data.batch_size=1",
    "model.channels=4",
    "model.num_keypoints=4",
    "model.hourglass_channels=4,4,4",
    "val_batches=1",
)
TRUE_JOINTS = (0, 2, 4, 6)  # the arm's joints that stand in for the four keypoints
BLENDER_FRAMES = (0, 11, 23)
SKIN_TOLERANCE = 1e-4  # of the body's size


def options(raw: Path, out: Path, **changes) -> RigOptions:
    base = RigOptions(
        source=raw,
        out=out,
        preset="tiny",
        steps=4,
        points=POINTS,
        fps=FPS,
        overrides=SMALL,
        progress=False,
    )
    return dataclasses.replace(base, **changes)


def cli_argv(raw: Path, out: Path, *extra) -> list[str]:
    argv = ["rig", "--from", raw, "--out", out, "--preset", "tiny", "--steps", 4]
    argv += ["--points", POINTS, "--fps", FPS, "--no-progress", *extra]
    argv += [a for s in SMALL for a in ("--set", s)]
    return [str(a) for a in argv]


def with_true_motion(work: Path, positions: np.ndarray) -> None:
    """Replaces WORK/motion.npz's keypoints by the arm's joints `TRUE_JOINTS` (module docstring),
    in the cube of the box the motion stage takes (the whole prepared sequence), alpha 1."""
    points = whole_sequence(CAPTURE, "reach", work / "data")
    bmin, scale = normalization_box(points)
    joints = apply_box(positions[:, TRUE_JOINTS], bmin[0, 0], scale[0, 0])
    keypoints = np.concatenate([joints, np.ones((*joints.shape[:2], 1))], axis=-1)
    with np.load(work / MOTION_FILE) as z:
        key = z["key"]
    np.savez(work / MOTION_FILE, keypoints=keypoints.astype(np.float32), key=key)


def make_capture(raw: Path, kind: str) -> dict:
    """The arm as .obj meshes in RAW/reach/ (one sequence folder in RAW), or as .ply points in
    a folder of its own handed over as RAW (`--from reach/`), one file a frame; the capture's
    RAW, the arm's motion and its frame-0 surface as the file holds it."""
    positions, rotations = arm_motion(FRAMES)
    if kind == "obj":
        paths = write_meshes(raw / "reach", arm_meshes(positions, rotations))
    else:
        paths = write_frames(raw / "reach", list(arm_points(positions, rotations, 300)), ".ply")
        raw = raw / "reach"
    first = trimesh.load(paths[0], process=False)
    faces = np.asarray(first.faces) if kind == "obj" else None
    return {"raw": raw, "positions": positions, "rest": np.asarray(first.vertices), "faces": faces}


def rigged(tmp_path_factory, kind: str, **changes) -> dict:
    """A capture of `kind`, rigged twice: trained, then with the arm's true motion (reused)."""
    root = tmp_path_factory.mktemp(f"rig-{kind}")
    out = root / "out" / f"{kind}.glb"
    capture = make_capture(root / "raw", kind)
    raw = capture["raw"]
    first = make_rig(options(raw, out, **changes))
    work = first.options.work_dir
    checkpoints = {p: p.stat().st_mtime_ns for p in (work / "skel").rglob("*") if p.is_file()}
    with_true_motion(work, capture["positions"])
    second = make_rig(options(raw, out, overwrite=True, **changes))
    return {**capture, "out": out, "first": first, "result": second, "checkpoints": checkpoints}


@pytest.fixture(scope="module")
def mesh_rig(tmp_path_factory):
    return rigged(tmp_path_factory, "obj")


# The point capture trains within `--minutes`: a 100 s step, whatever this machine does, makes
# 7.5 minutes fit 4 steps (with the 8% kept for compiling and validating), far more time than
# the tiny steps take here; its rerun keeps the budget and trains nothing.
MINUTES, STEP_S = 7.5, 100.0


@pytest.fixture(scope="module")
def point_rig(tmp_path_factory):
    from nmjax import bench

    timed = {"compute_s_median": STEP_S - 0.2, "load_s_per_step": 0.2}
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(bench, "bench_skel", lambda *args, **kwargs: timed)
        return rigged(tmp_path_factory, "ply", units="cm", steps=None, minutes=MINUTES)


def size_of(x: np.ndarray) -> float:
    return float(np.max(np.ptp(np.asarray(x).reshape(-1, 3), axis=0)))


def to_capture(x: np.ndarray) -> np.ndarray:
    """Coordinates of a file (+Y up) back in the arm's own axes (z up)."""
    return np.asarray(x) @ file_axes(2)


# --- what the files hold --------------------------------------------------------------------------


@pytest.mark.parametrize("which", ["mesh_rig", "point_rig"])
def test_the_rig_plays_every_frame_in_the_captures_units_up_turned_to_y(which, request):
    case = request.getfixturevalue(which)
    result, positions = case["result"], case["positions"]
    rig = result.rig
    glb, bvh, png = result.options.outputs
    assert glb.is_file() and bvh.is_file() and png.is_file()
    assert rig.num_frames == FRAMES and rig.frame_rate == FPS
    # The skinned surface is frame 0 of the capture as given, turned to +Y up.
    np.testing.assert_allclose(to_capture(rig.vertices), case["rest"], atol=1e-9)
    if case["faces"] is None:
        assert rig.faces is None
    else:
        np.testing.assert_array_equal(rig.faces, case["faces"])
    # Keypoints mapped out of the cube by the motion stage's box: the arm's joints in its units.
    size = size_of(positions)
    true = positions[:, TRUE_JOINTS][:, rig.joints]
    np.testing.assert_allclose(to_capture(rig.positions), true, atol=1e-5 * size)
    # The file holds the same: every frame keyed at frame / fps, every joint where nmjax has it.
    read = gltf.read(glb)
    np.testing.assert_allclose(read.times, np.arange(FRAMES) / FPS, atol=1e-6)
    np.testing.assert_allclose(read.positions, rig.positions, atol=1e-5 * size)
    motion = skinned_surface(rig, rig.vertices, rig.weights)
    np.testing.assert_allclose(read.vertices, motion, atol=SKIN_TOLERANCE * size)
    assert bvh.read_text().count("\n") >= FRAMES and f"Frames: {FRAMES}" in bvh.read_text()


def test_a_mesh_capture_is_skinned_as_its_frame_0_mesh(mesh_rig):
    doc = pygltflib.GLTF2.load_binary(mesh_rig["out"])
    (primitive,) = doc.meshes[0].primitives
    assert primitive.mode == pygltflib.TRIANGLES and primitive.indices is not None
    assert len(doc.skins) == 1 and len(doc.animations) == 1
    report = validate(mesh_rig["out"])
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"]


def test_a_point_capture_is_skinned_as_glTF_points(point_rig):
    doc = pygltflib.GLTF2.load_binary(point_rig["out"])
    (primitive,) = doc.meshes[0].primitives
    assert primitive.mode == pygltflib.POINTS and primitive.indices is None
    assert gltf.read(point_rig["out"]).faces is None
    report = validate(point_rig["out"])
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"]
    summary = point_rig["result"].summary()
    assert "skinned points: 300 vertices" in summary and "lengths in cm" in summary
    meta = json.loads((point_rig["result"].options.work_dir / "data" / "meta.json").read_text())
    assert (meta["units"], meta["fps"]) == ("cm", FPS)


def test_view_plays_a_point_rig_as_moving_points(point_rig):
    from nmjax import view

    read = gltf.read(point_rig["out"])
    viewer = view.open_view(point_rig["out"], port=0)
    try:
        assert viewer.num_frames == FRAMES and "/gltf/points" in viewer.nodes
        viewer.frame.value = 5  # the slider redraws
        # viser keeps a point cloud's positions in float16 (its default precision).
        size = size_of(read.vertices)
        np.testing.assert_allclose(
            np.asarray(viewer.mesh.points), read.vertices[5], atol=2e-3 * size
        )
    finally:
        viewer.stop()


def test_the_summary_names_joints_frames_files_time_and_fit_error(mesh_rig):
    result = mesh_rig["first"]
    lines = result.summary().splitlines()
    assert lines[0].startswith(f"nmjax rig: {mesh_rig['out']}") and "(sequence reach)" in lines[0]
    text = "\n".join(lines)
    assert re.search(r"joints: \d+ kept of the 4 keypoints \(phase 1 trained, 4 steps", text)
    assert f"frames: {FRAMES} at 24 fps, every frame of the capture" in text
    assert "+Y up (the capture's z), lengths in m" in text
    assert re.search(r"fit error: [\d.]+ x1e-4 in the normalised cube, [\d.e+-]+ m\^2", text)
    for path in result.options.outputs:
        assert str(path) in text
    assert np.isfinite(result.fit["cd"]) and result.fit["cd"] > 0
    assert result.fit["frames"] == FRAMES


# --- the work folder: reused, resumed --------------------------------------------------------


def test_minutes_fit_the_steps_to_the_budget_and_a_rerun_keeps_them(point_rig):
    first, again = point_rig["first"], point_rig["result"]
    assert (first.phase1, first.steps) == ("trained", 4)  # floor(7.5 x 60 / (100 x 1.08))
    saved = run_folder.load_config(first.skel_run, SkelTrainConfig)
    assert saved.loop.steps == 4 and 7.0 < saved.loop.time_limit_minutes <= MINUTES
    assert (again.phase1, again.steps) == ("reused", 4)


def test_a_rerun_reuses_every_stage_and_trains_nothing(mesh_rig):
    result = mesh_rig["result"]
    assert set(result.reused) == {"prepare", "phase1", "motion"}
    assert result.phase1 == "reused" and result.steps == 4
    work = result.options.work_dir
    now = {p: p.stat().st_mtime_ns for p in (work / "skel").rglob("*") if p.is_file()}
    assert now == mesh_rig["checkpoints"]


def test_the_same_command_resumes_its_phase_1_run_and_then_reuses_it(mesh_rig, tmp_path, capsys):
    work = tmp_path / "work"
    shutil.copytree(mesh_rig["result"].options.work_dir, work)
    out = tmp_path / "again.glb"
    argv = cli_argv(mesh_rig["raw"], out, "--work", work)
    argv[argv.index("--steps") + 1] = "8"
    assert nmjax_main(argv) == 0
    printed = capsys.readouterr().out
    assert "(phase 1 resumed from step 4, 8 steps" in printed
    assert run_folder.checkpoint_steps(work / "skel")[-1] == 8
    assert nmjax_main([*argv, "--overwrite"]) == 0
    printed = capsys.readouterr().out
    assert "(phase 1 reused, 8 steps" in printed and "prepare" in printed
    assert "phase1 " in printed and "(reused)" in printed


# --- bad input: one line, exit 2, nothing left behind ----------------------------------------


def refused(capsys, argv: list[str], *, watch: Path) -> str:
    """Runs `nmjax rig argv`, which must fail with one line and exit 2 and leave `watch` as it
    was (every file in it, with its size and time); returns the line."""
    before = {p: (p.stat().st_size, p.stat().st_mtime_ns) for p in watch.rglob("*")}
    assert nmjax_main(argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("nmjax rig"), captured.err
    assert {p: (p.stat().st_size, p.stat().st_mtime_ns) for p in watch.rglob("*")} == before
    return lines[0]


BAD_CAPTURES = [
    ("nan-ply", r"frame_003\.ply: NaN at vertex 7 "),
    ("inf-xyz", r"frame_003\.xyz: inf at vertex 7 "),
    ("nan-npy-frame", r"frame_003\.npy: NaN at vertex 7 "),
    ("nan-obj", r"frame_002\.obj: NaN at vertex 5 "),
    ("nan-array", r"wave\.npz: NaN at frame 2, vertex 5 "),
    ("junk-xyz", r"frame_002\.xyz as `x y z` point lines"),
    ("two-columns", r"frame_000\.txt as `x y z` point lines"),
    ("empty-ply", r"frame_001\.ply holds no vertices"),
    ("junk-ply", r"cannot read the mesh .*frame_001\.ply"),
    ("mixed", r"frame_002\.ply is a mesh .* while frame_000\.ply is a point cloud"),
    ("two-arrays", r"wave\.npz holds the arrays \['a', 'b'\]"),
    ("flat-array", r"wave\.npy holds an array of shape \(4, 300, 2\)"),
    ("one-frame", r"fewer than 2 frames: \['wave'\]"),
    ("folder-and-array", r"'wave' is both a folder of frames and wave\.npy"),
    ("empty-folder", r"no sub-folder holds"),
]


@pytest.mark.parametrize("case, match", BAD_CAPTURES)
def test_what_prepare_data_refuses_is_refused_before_training(tmp_path, capsys, case, match):
    raw, out = tmp_path / "raw", tmp_path / "out" / "rig.glb"
    bad_capture(raw, case)
    line = refused(capsys, cli_argv(raw, out), watch=tmp_path)
    assert re.search(match, line), line
    assert not (tmp_path / "out").exists()  # no files, no work folder, no training


def test_a_split_json_naming_a_missing_sequence_is_refused(tmp_path, capsys):
    raw, out = tmp_path / "raw", tmp_path / "out" / "rig.glb"
    for seq in ("reach", "wave"):
        write_frames(raw / seq, list(arm_points(*arm_motion(4), 100)), ".ply")
    (raw / "split.json").write_text(json.dumps({"train": ["reach"], "test": ["wave", "jump"]}))
    line = refused(capsys, cli_argv(raw, out), watch=tmp_path)
    assert "jump" in line and "split.json" in line
    assert not (tmp_path / "out").exists()


def test_a_capture_without_a_test_sequence_is_refused_before_training(tmp_path, capsys):
    raw, out = tmp_path / "raw", tmp_path / "out" / "rig.glb"
    for seq in ("reach", "wave"):
        write_frames(raw / seq, list(arm_points(*arm_motion(4), 100)), ".ply")
    (raw / "split.json").write_text(json.dumps({"train": ["reach", "wave"], "test": []}))
    line = refused(capsys, cli_argv(raw, out), watch=tmp_path)
    assert "'test'" in line
    assert not (tmp_path / "out").exists()


@pytest.fixture
def capture(tmp_path) -> Path:
    """A small point capture of two sequences (nothing is trained on it here)."""
    raw = tmp_path / "raw"
    for seq in ("reach", "wave"):
        write_frames(raw / seq, list(arm_points(*arm_motion(4), 100)), ".ply")
    return raw


@pytest.mark.parametrize("existing", ["rig.glb", "rig.bvh", "rig.png"])
def test_an_existing_output_without_overwrite_is_refused(tmp_path, capsys, capture, existing):
    out = tmp_path / "out" / "rig.glb"
    out.parent.mkdir()
    (out.parent / existing).write_bytes(b"mine")
    line = refused(capsys, cli_argv(capture, out), watch=tmp_path)
    assert f"{out.parent / existing} exists; pass --overwrite" in line
    assert sorted(p.name for p in out.parent.iterdir()) == [existing]


def test_bad_options_are_refused_before_anything_is_written(tmp_path, capsys, capture):
    out = tmp_path / "out" / "rig.glb"
    point_cloud = tmp_path / "cloud.ply"
    shutil.copy(capture / "reach" / "frame_000.ply", point_cloud)
    broken = tmp_path / "broken.obj"
    broken.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    cases = [
        (["--seq", "jump"], "--seq 'jump' is not a sequence of"),
        (["--mesh", tmp_path / "none.obj"], "none.obj does not exist"),
        (["--mesh", point_cloud], "has no faces: it is a point cloud of 100 points"),
        (["--mesh", broken], "broken.obj: NaN at vertex 2"),
        (["--set", "model.nope=1"], "nope"),
        (["--up", "w"], "--up"),
        (["--units", "furlong"], "--units"),
        (["--fps", "0"], "--fps must be > 0"),
        (["--points", "0"], "--points"),
    ]
    for extra, named in cases:
        line = refused(capsys, cli_argv(capture, out, *extra), watch=tmp_path)
        assert named in line, (extra, line)
        assert not (tmp_path / "out").exists()
    for name in ("rig.gltf", "rig"):
        line = refused(capsys, cli_argv(capture, tmp_path / "out" / name), watch=tmp_path)
        assert "give a file ending in .glb" in line


def test_a_work_folder_of_other_settings_or_no_rig_is_refused(mesh_rig, tmp_path, capsys):
    work = mesh_rig["result"].options.work_dir
    out = tmp_path / "other.glb"
    argv = cli_argv(mesh_rig["raw"], out, "--work", work)
    argv[argv.index("--points") + 1] = "300"
    line = refused(capsys, argv, watch=work)
    assert "holds the rig of other settings: points (there: 400, asked: 300)" in line
    other = tmp_path / "mine"
    other.mkdir()
    (other / "notes.txt").write_text("not a work folder")
    line = refused(capsys, cli_argv(mesh_rig["raw"], out, "--work", other), watch=tmp_path)
    assert "holds files but no rig.json" in line
    assert not out.exists()


# --- Blender ------------------------------------------------------------------------------------


BLENDER_SCRIPT = Path(__file__).with_name("blender_rig.py")


def open_in_blender(result, tmp_path: Path) -> dict:
    """What headless Blender makes of the rig's .glb and .bvh (`blender_rig.py`)."""
    blender = require_program(
        ["blender"],
        "the rig's Blender test opens the .glb and .bvh in headless Blender",
        "apt-get install blender python3-numpy",
    )
    glb, bvh, _ = result.options.outputs
    report = tmp_path / "blender.json"
    argv = [blender, "-b", "--factory-startup", "--python", BLENDER_SCRIPT, "--"]
    argv += [glb, bvh, result.rig.frame_rate, report, *BLENDER_FRAMES]
    done = subprocess.run(
        [str(a) for a in argv], capture_output=True, text=True, timeout=300, check=False
    )
    assert done.returncode == 0 and report.is_file(), done.stdout[-3000:] + done.stderr[-3000:]
    return json.loads(report.read_text())


def from_blender(x) -> np.ndarray:
    """Blender's +Z-up world coordinates back in glTF's +Y-up ones."""
    x = np.asarray(x, np.float64)
    return np.stack([x[..., 0], x[..., 2], -x[..., 1]], axis=-1)


@pytest.mark.parametrize("which", ["mesh_rig", "point_rig"])
def test_blender_deforms_the_rig_as_nmjax_skins_it(which, request, tmp_path):
    result = request.getfixturevalue(which)["result"]
    report = open_in_blender(result, tmp_path)
    rig = result.rig
    (armature,) = report["armatures"]
    (mesh,) = report["meshes"]
    assert {"type": "ARMATURE", "object": armature} in mesh["modifiers"]
    first, last = report["action"]["frame_range"]
    assert last - first + 1 == FRAMES
    size = size_of(rig.vertices)
    np.testing.assert_allclose(from_blender(report["rest"]), rig.vertices, atol=1e-6 * size)
    frames = np.asarray(BLENDER_FRAMES)
    posed = dataclasses.replace(
        rig, positions=rig.positions[frames], rotations=rig.rotations[frames]
    )
    ours = skinned_surface(posed, rig.vertices, rig.weights)
    for i, frame in enumerate(BLENDER_FRAMES):
        theirs = from_blender(report["posed"][str(frame)])
        np.testing.assert_allclose(theirs, ours[i], atol=SKIN_TOLERANCE * size, err_msg=str(frame))
    # The motion turns the bones: the check above is not one of a mesh standing still.
    assert np.abs(ours[-1] - ours[0]).max() > 0.05 * size
    # Blender's BVH importer reads the same joints and every frame.
    assert sorted(report["bvh"]["bones"]) == sorted(rig.names)
    first, last = report["bvh"]["frame_range"]
    assert last - first + 1 == FRAMES


# --- the benchmark script ---------------------------------------------------------------------


@pytest.mark.slow  # trains a third capture and compiles the step it times: minutes on 2 cores
def test_the_rig_benchmark_runs_at_a_tiny_size(capsys):
    from experiment_scripts import load_experiment

    argv = ["--preset", "tiny", "--frames", "12", "--points", "200", "--vertices", "3000"]
    argv += ["--train-steps", "2", "--step-steps", "1", *(a for s in SMALL for a in ("--set", s))]
    rows = load_experiment("bench_rig.py").main(argv)
    assert set(rows["stage_s"]) == {
        "prepare", "skeleton", "motion", "skin", "fit", "write", "picture"
    }  # fmt: skip
    assert all(v >= 0 for v in rows["stage_s"].values())
    assert rows["beyond_training_s"] == pytest.approx(sum(rows["stage_s"].values()))
    assert rows["mesh_vertices"] >= 3000 and rows["frames"] == 12
    assert rows["phase1_steps"] == 20 and rows["step_s"] > 0  # the tiny preset's 20 steps
    assert rows["training_min"] * 60 >= 20 * rows["step_s"]
    printed = capsys.readouterr().out
    assert "beyond training" in printed and "phase 1 (derived): 20 steps" in printed
