"""A user's own capture through `nmjax prepare-data --from RAW` (no --data) and `nmjax train-skel
--root OUT`: point-cloud frames in every format, resampling, the capture's meta.json, the split
of a single sequence, and each bad input as one line with exit status 2 and nothing left in OUT.
The captures are synthetic arm bodies (`nmjax.data.synthetic.simulate`) written in the test."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from captures import bad_capture, body, write_frames

from nmjax import run_folder
from nmjax.cli import main as nmjax_main
from nmjax.data import layout, prepare
from nmjax.data.datasets import load_sequences
from nmjax.data.streaming import sequence_seeds

POINTS = 256


def prepare_capture(*argv) -> int:
    return nmjax_main(["prepare-data", *map(str, argv)])


def one_error(capsys) -> str:
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("nmjax prepare-data")
    return lines[0]


def nothing_left(out: Path) -> bool:
    """No finished set and no partial file under `out` (absent, or holding nothing)."""
    return not out.exists() or not any(out.rglob("*"))


def distance_to(points: np.ndarray, cloud: np.ndarray) -> np.ndarray:
    """(P,) distance of each point to its nearest point of `cloud` (N, 3)."""
    return np.sqrt(((points[:, None] - cloud[None].astype(np.float32)) ** 2).sum(-1)).min(1)


# --- point clouds in --------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".ply", ".xyz", ".txt", ".npy"])
def test_point_frames_of_every_format_are_resampled_to_the_points_asked_for(tmp_path, suffix):
    raw, out = tmp_path / "raw", tmp_path / "out"
    # Two sequences whose frames hold 200..380 points: fewer and more than POINTS.
    clouds = {seq: body(5, 400, seed) for seq, seed in (("reach", 0), ("wave", 1))}
    ragged = {seq: [x[: 200 + 45 * t] for t, x in enumerate(c)] for seq, c in clouds.items()}
    for seq, frames in ragged.items():
        write_frames(raw / seq, frames, suffix)
    (raw / "reach" / "readme.txt").write_text("no frame number: not a frame\n")
    assert prepare_capture("--from", raw, "--root", out, "--points", POINTS) == 0
    meta = json.loads((out / "meta.json").read_text())
    assert meta["name"] == layout.CAPTURE and meta["frames"] == {"reach": 5, "wave": 5}
    loaded = {s.name: s for split in layout.SPLITS for s in load_sequences("capture", split, out)}
    assert sorted(loaded) == ["reach", "wave"]
    for seq, frames in ragged.items():
        vertices = np.asarray(loaded[seq].vertices)
        assert vertices.shape == (5, POINTS, 3)
        for t, cloud in enumerate(frames):
            # Every point is one of the frame's own; a frame of more points gives distinct ones,
            # a frame of fewer keeps all of its own.
            assert distance_to(vertices[t], cloud).max() < 1e-5
            if len(cloud) >= POINTS:
                assert len(np.unique(vertices[t], axis=0)) == POINTS
            else:
                assert distance_to(cloud.astype(np.float32), vertices[t]).max() < 1e-5


def test_a_folder_of_frames_handed_over_as_it_is_is_one_sequence(tmp_path):
    raw, out = tmp_path / "wave", tmp_path / "out"
    frames = list(body(4, POINTS))
    write_frames(raw, frames, ".ply")
    (raw / "readme.txt").write_text("no frame number: not a frame\n")
    assert list(prepare.find_sequences(raw)) == ["wave"]
    assert prepare_capture("--from", raw, "--root", out, "--points", POINTS) == 0
    meta = json.loads((out / "meta.json").read_text())
    assert meta["frames"] == {"wave": 4, "wave_test": 4}  # too short to cut: a copy
    (seq,) = load_sequences("capture", "train", out)
    np.testing.assert_array_equal(seq.vertices, frames)
    # .npy files directly in RAW stay (T, N, 3) arrays, one sequence each.
    arrays = tmp_path / "arrays"
    arrays.mkdir()
    np.save(arrays / "frame_000.npy", frames[0])
    with pytest.raises(ValueError, match=r"frame_000\.npy holds an array of shape \(256, 3\)"):
        prepare.raw_sequences(arrays)


@pytest.mark.parametrize("suffix", [".npy", ".npz"])
def test_one_array_per_sequence(tmp_path, suffix):
    raw, out = tmp_path / "raw", tmp_path / "out"
    raw.mkdir()
    arrays = {"reach": body(4, 300, 0), "wave": body(6, 300, 1)}
    for seq, points in arrays.items():
        if suffix == ".npy":
            np.save(raw / f"{seq}.npy", points)
        else:
            np.savez(raw / f"{seq}.npz", points=points, normals=np.zeros_like(points))
    assert prepare_capture("--from", raw, "--root", out, "--points", POINTS) == 0
    assert json.loads((out / "meta.json").read_text())["format"] == "point-arrays"
    for split in layout.SPLITS:
        for seq in load_sequences("capture", split, out):
            original = arrays[seq.name]
            assert seq.vertices.shape == (len(original), POINTS, 3)
            for t in range(len(original)):
                assert distance_to(np.asarray(seq.vertices[t]), original[t]).max() < 1e-6


def test_resampling_is_seeded_and_keeps_the_frame_when_counts_agree():
    cloud = body(1, 300)[0]
    np.testing.assert_array_equal(prepare.resample_points(cloud, 300, 5), cloud)
    fewer = prepare.resample_points(cloud, 100, 5)
    np.testing.assert_array_equal(fewer, prepare.resample_points(cloud, 100, 5))
    assert not np.array_equal(fewer, prepare.resample_points(cloud, 100, 6))
    assert len(np.unique(fewer, axis=0)) == 100
    more = prepare.resample_points(cloud, 500, 5)
    np.testing.assert_array_equal(more[:300], cloud)  # every point once, then drawn again
    assert more.shape == (500, 3) and distance_to(more, cloud).max() == 0


def test_same_seed_same_bytes_other_seed_other_points(tmp_path):
    raw = tmp_path / "raw"
    write_frames(raw / "reach", list(body(3, 400)), ".xyz")
    write_frames(raw / "wave", list(body(3, 400, 1)), ".xyz")
    written = []
    for name, seed in (("a", 0), ("b", 0), ("c", 1)):
        out = tmp_path / name
        assert prepare_capture("--from", raw, "--root", out, "--points", 100, "--seed", seed) == 0
        written.append(next(out.rglob("reach.npy")).read_bytes())
    assert written[0] == written[1] != written[2]


# --- the capture under its own name ------------------------------------------------------------


def test_meta_json_records_up_fps_units_and_train_config_reads_them(tmp_path, capsys):
    raw, out = tmp_path / "raw", tmp_path / "out"
    write_frames(raw / "reach", list(body(3)), ".ply")
    write_frames(raw / "wave", list(body(3, seed=1)), ".ply")
    argv = ["--from", raw, "--root", out, "--points", 64, "--up", "y", "--fps", 24, "--units", "cm"]
    assert prepare_capture(*argv) == 0
    assert f"prepared capture in {out}" in capsys.readouterr().out
    meta = json.loads((out / "meta.json").read_text())
    assert (meta["up"], meta["fps"], meta["units"], meta["metres_per_unit"]) == (
        "y",
        24.0,
        "cm",
        0.01,
    )
    cfg = layout.training_config(root=out)
    assert (cfg.data.name, cfg.data.root, cfg.data.up_axis, cfg.data.fps) == (
        "capture",
        str(out),
        1,
        24.0,
    )
    # The generic spec's recipe, and none of a built-in set's.
    assert (cfg.loop.epochs, cfg.loop.steps, cfg.optim.lr_milestones) == (0, 20_000, (6000, 14000))
    assert cfg.optim.optimizer_reset == "never" and cfg.model.num_keypoints == 24
    assert (cfg.weights.vol, cfg.weights.traj, cfg.weights.local) == (10.0, 1.0, 1e-3)
    # Defaults: z up, 30 fps, metres.
    again = tmp_path / "again"
    assert prepare_capture("--from", raw, "--root", again, "--points", 64) == 0
    meta = json.loads((again / "meta.json").read_text())
    assert (meta["up"], meta["fps"], meta["units"]) == ("z", 30.0, "m")
    assert layout.training_config(root=again).data.up_axis == 2


def test_a_built_in_name_keeps_its_own_rate_and_axes(tmp_path, capsys):
    raw, out = tmp_path / "raw", tmp_path / "out"
    write_frames(raw / "reach", list(body(3)), ".ply")
    assert prepare_capture("--data", "panda", "--from", raw, "--root", out, "--fps", 24) == 2
    line = one_error(capsys)
    assert "--fps" in line and "panda" in line and nothing_left(out)
    assert prepare_capture("--root", out) == 2
    assert "--from RAW" in one_error(capsys)


# --- a single capture -------------------------------------------------------------------------


def test_a_single_sequence_holds_out_its_last_frames_as_its_test(tmp_path, capsys):
    raw, out = tmp_path / "raw", tmp_path / "out"
    frames = list(body(40, 300))
    write_frames(raw / "wave", frames, ".npy")
    assert prepare_capture("--from", raw, "--root", out, "--points", 300) == 0
    line = capsys.readouterr().out
    assert "train 1 / test 1" in line and "last 10 of 40 frames" in line and "wave_test" in line
    (train,) = load_sequences("capture", "train", out)
    (test,) = load_sequences("capture", "test", out)
    assert (train.name, train.num_frames, test.name, test.num_frames) == (
        "wave",
        30,
        "wave_test",
        10,
    )
    # 300 points a frame: the frames as captured, in order, split at frame 30.
    np.testing.assert_array_equal(np.concatenate([train.vertices, test.vertices]), frames)
    meta = json.loads((out / "meta.json").read_text())
    assert meta["cut_from"] == {
        "wave": {"sequence": "wave", "frames": [0, 30]},
        "wave_test": {"sequence": "wave", "frames": [30, 40]},
    }


def test_the_parts_of_a_single_sequence_keep_its_own_sampling(tmp_path):
    raw, out = tmp_path / "raw", tmp_path / "out"
    frames = list(body(24, 300))
    write_frames(raw / "wave", frames, ".xyz")
    assert prepare_capture("--from", raw, "--root", out, "--points", 100, "--seed", 3) == 0
    (test,) = load_sequences("capture", "test", out)
    seeds = sequence_seeds(3, "wave", 24)
    assert test.num_frames == 10  # at least one training crop of 10 frames, though 10% is 3
    for t in range(10):
        expected = prepare.resample_points(
            np.loadtxt(raw / "wave" / f"frame_{14 + t:03d}.xyz"), 100, int(seeds[14 + t])
        )
        np.testing.assert_array_equal(test.vertices[t], expected)


def test_a_single_short_sequence_is_scored_on_a_copy_and_says_so(tmp_path, capsys):
    raw, out = tmp_path / "raw", tmp_path / "out"
    write_frames(raw / "wave", list(body(12, 200)), ".ply")
    assert prepare_capture("--from", raw, "--root", out, "--points", 200) == 0
    line = capsys.readouterr().out
    assert "train 1 / test 1" in line and "copy" in line and "training frames" in line
    (train,) = load_sequences("capture", "train", out)
    (test,) = load_sequences("capture", "test", out)
    assert train.num_frames == test.num_frames == 12
    np.testing.assert_array_equal(train.vertices, test.vertices)


def test_no_test_sequence_is_never_shown_without_what_follows(tmp_path, capsys):
    raw, out = tmp_path / "raw", tmp_path / "out"
    for seq, seed in (("reach", 0), ("wave", 1)):
        write_frames(raw / seq, list(body(3, seed=seed)), ".ply")
    (raw / "split.json").write_text(json.dumps({"train": ["reach", "wave"], "test": []}))
    assert prepare_capture("--from", raw, "--root", out, "--points", 64) == 0
    line = capsys.readouterr().out
    assert "test 0" in line and "train-skel stops" in line
    assert str(raw / "split.json") in line


def test_split_json_naming_a_sequence_raw_lacks_is_refused_with_the_name(tmp_path, capsys):
    raw, out = tmp_path / "raw", tmp_path / "out"
    for seq, seed in (("reach", 0), ("wave", 1)):
        write_frames(raw / seq, list(body(3, seed=seed)), ".ply")
    (raw / "split.json").write_text(json.dumps({"train": ["reach"], "test": ["wave", "jump"]}))
    assert prepare_capture("--from", raw, "--root", out, "--points", 64) == 2
    line = one_error(capsys)
    assert "'jump'" not in line and "jump" in line and "split.json" in line
    assert nothing_left(out)


# --- bad input: one line, exit 2, nothing left in OUT ----------------------------------------


@pytest.mark.parametrize(
    "case, match",
    [
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
    ],
)
def test_bad_capture_is_one_line_and_leaves_nothing(tmp_path, capsys, case, match):
    raw, out = tmp_path / "raw", tmp_path / "out"
    bad_capture(raw, case)
    assert prepare_capture("--from", raw, "--root", out, "--points", 64) == 2
    line = one_error(capsys)
    assert re.search(match, line), line
    assert "no surface" not in line
    assert nothing_left(out)


@pytest.mark.parametrize(
    "argv, match",
    [
        (["--fps", "0"], "--fps must be > 0"),
        (["--units", "furlong"], "--units"),
        (["--up", "w"], "--up"),
        (["--subjects", "50002"], "--subjects"),
    ],
)
def test_bad_capture_options_are_one_line(tmp_path, capsys, argv, match):
    raw, out = tmp_path / "raw", tmp_path / "out"
    write_frames(raw / "wave", list(body(3)), ".ply")
    assert prepare_capture("--from", raw, "--root", out, *argv) == 2
    line = capsys.readouterr().err.strip()
    assert "\n" not in line and match in line and nothing_left(out)


# --- training a prepared capture ---------------------------------------------------------------


def test_train_skel_reads_the_spec_up_axis_and_rate_from_the_prepared_folder(tmp_path):
    raw, out, run = tmp_path / "raw", tmp_path / "out", tmp_path / "run"
    write_frames(raw / "wave", list(body(24, 400)), ".ply")
    assert (
        prepare_capture("--from", raw, "--root", out, "--points", 400, "--up", "y", "--fps", 24)
        == 0
    )
    # The tiny preset at the tests' G=8 size (tests/tiny_configs.py), a few steps.
    small = ["data.grid=8", "model.grid=8", "data.frames=3", "data.batch_size=1"]
    small += ["model.channels=4", "model.num_keypoints=4", "model.hourglass_channels=4,4,4"]
    small += ["val_batches=1"]
    argv = ["train-skel", "--root", str(out), "--preset", "tiny", "--steps", "4", "--run", str(run)]
    argv += ["--no-progress", *(a for s in small for a in ("--set", s))]
    assert nmjax_main(argv) == 0
    saved = json.loads((run / "config.json").read_text())["data"]
    assert (saved["name"], saved["root"], saved["up_axis"], saved["fps"]) == (
        "capture",
        str(out),
        1,
        24.0,
    )
    assert run_folder.motion_format(run) == (24.0, 1)
    assert set(run_folder.load_trajectories(run, "test")) == {"wave_test"}


def test_train_skel_on_a_folder_without_a_prepared_set_is_one_line(tmp_path, capsys):
    assert nmjax_main(["train-skel", "--root", str(tmp_path), "--preset", "tiny"]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "no prepared dataset" in line and "prepare-data --from RAW" in line
