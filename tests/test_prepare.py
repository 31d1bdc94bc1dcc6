"""`nmjax prepare-data` round trip on small mesh sequences made with trimesh primitives."""

from __future__ import annotations

import json
import re
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import trimesh

from nmjax.cli import main as nmjax_main
from nmjax.data.datasets import load_sequences
from nmjax.data.layout import split_by_frames

POINTS = 300


def prepare_main(argv: list[str]) -> int:
    return nmjax_main(["prepare-data", *argv])


HALF = 0.5  # half extent of the unit box


def box_at(t: int) -> trimesh.Trimesh:
    """Unit box moved by t along x: frame t's points have x in [t - 0.5, t + 0.5]."""
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    box.apply_translation((float(t), 0.0, 0.0))
    return box


def write_raw(source: Path, frames: dict[str, int], joints_for: tuple[str, ...] = ()) -> None:
    suffixes = (".obj", ".ply", ".off")
    for s, (seq, count) in enumerate(frames.items()):
        folder = source / seq
        folder.mkdir(parents=True)
        for t in range(count):
            # Unpadded numbers: frame_10 must come after frame_9, not after frame_1.
            box_at(t).export(folder / f"frame_{t}{suffixes[(s + t) % 3]}")
        if seq in joints_for:
            joints = np.stack([np.full((2, 3), float(t)) for t in range(count)])
            np.save(folder / "joints.npy", joints.astype(np.float64))
        (folder / "notes.txt").write_text("ignored: not a mesh")


def test_round_trip(tmp_path):
    source, root = tmp_path / "raw", tmp_path / "out"
    frames = {"jump": 11, "walk": 3, "run": 4}
    write_raw(source, frames, joints_for=("jump",))
    argv = ["--data", "dfaust", "--from", str(source), "--root", str(root), "--points"]
    assert prepare_main([*argv, str(POINTS)]) == 0
    split = split_by_frames(frames)
    assert json.loads((root / "split.json").read_text()) == split
    meta = json.loads((root / "meta.json").read_text())
    assert meta["sample_rate"] == 5 and meta["points"] == POINTS and meta["frames"] == frames
    loaded = {}
    for name in ("train", "test"):
        sequences = load_sequences("dfaust", name, root)
        assert sorted(s.name for s in sequences) == split[name]
        loaded.update({s.name: s for s in sequences})
    assert set(loaded) == set(frames)
    for seq, count in frames.items():
        vertices = np.asarray(loaded[seq].vertices)
        assert vertices.shape == (count, POINTS, 3) and vertices.dtype == np.float32
        t = np.arange(count, dtype=np.float32)[:, None]
        # Frames in natural order, every point on the surface of its frame's box.
        assert np.all(np.abs(vertices[..., 0] - t) <= HALF + 1e-5)
        assert np.all(np.abs(vertices[..., 1:]) <= HALF + 1e-5)
        offset = vertices - np.stack([t, 0 * t, 0 * t], axis=-1)
        on_face = np.isclose(np.abs(offset), HALF, atol=1e-5).any(axis=-1)
        assert on_face.all()
    np.testing.assert_array_equal(loaded["jump"].joints[:, 0, 0], np.arange(11))
    assert loaded["walk"].joints is None
    # Same seed, same bytes; another seed samples other points.
    again = tmp_path / "again"
    assert prepare_main([*argv[:-3], "--root", str(again), "--points", str(POINTS)]) == 0
    split_dir = "train" if "walk" in split["train"] else "test"
    first = (root / split_dir / "vertices" / "walk.npy").read_bytes()
    assert (again / split_dir / "vertices" / "walk.npy").read_bytes() == first
    other = tmp_path / "other"
    argv_other = [*argv[:-3], "--root", str(other), "--points", str(POINTS), "--seed", "1"]
    assert prepare_main(argv_other) == 0
    assert (other / split_dir / "vertices" / "walk.npy").read_bytes() != first


def test_split_file_limits_and_hanco_names(tmp_path):
    source, root = tmp_path / "raw", tmp_path / "hanco"
    write_raw(source, {"0001": 4, "0002": 5, "0003": 3}, joints_for=("0001", "0002"))
    (source / "split.json").write_text(json.dumps({"train": ["0001", "0003"], "test": ["0002"]}))
    code = nmjax_main(
        ["prepare-data", "--data", "hanco", "--from", str(source), "--root", str(root)]
        + ["--points", "50", "--sequences", "2", "--frames", "3"]
    )
    assert code == 0
    assert json.loads((root / "split.json").read_text()) == {"train": ["0001"], "test": ["0002"]}
    assert (root / "test" / "joints" / "0002_joints.npy").is_file()
    (seq,) = load_sequences("hanco", "test", root)
    assert seq.vertices.shape == (3, 50, 3) and seq.joints.shape == (3, 2, 3)
    np.testing.assert_array_equal(seq.joints[:, 0, 0], [0, 1, 2])


def test_existing_dataset_needs_overwrite(tmp_path, capsys):
    source, root = tmp_path / "raw", tmp_path / "out"
    write_raw(source, {"a": 3, "b": 3})
    argv = ["--data", "panda", "--from", str(source), "--root", str(root), "--points", "20"]
    assert prepare_main(argv) == 0
    stamp = (root / "meta.json").stat().st_mtime_ns
    assert prepare_main(argv) == 0
    assert "--overwrite" in capsys.readouterr().out
    assert (root / "meta.json").stat().st_mtime_ns == stamp
    (root / "train" / "vertices" / "stale.npy").write_bytes(b"old")
    assert prepare_main([*argv, "--overwrite"]) == 0
    assert not (root / "train" / "vertices" / "stale.npy").exists()


@pytest.mark.parametrize(
    "case, match",
    [
        ("missing-from", "no such folder"),
        ("no-meshes", "no sub-folder holds"),
        ("one-frame", "fewer than 2 frames"),
        ("bad-joints", r"joints.npy: joints must have shape \(T, J, 3\) with T = 3"),
        ("no-surface", "cannot read the mesh|no surface"),
        ("unlisted", "in neither split"),
    ],
)
def test_bad_raw_input(tmp_path, capsys, case, match):
    source, root = tmp_path / "raw", tmp_path / "out"
    if case != "missing-from":
        source.mkdir()
    if case == "no-meshes":
        (source / "seq").mkdir()
        (source / "seq" / "readme.txt").write_text("x")
    if case == "one-frame":
        write_raw(source, {"a": 1})
    if case == "bad-joints":
        write_raw(source, {"a": 3})
        np.save(source / "a" / "joints.npy", np.zeros((2, 4, 3)))
    if case == "no-surface":
        write_raw(source, {"a": 2})
        (source / "a" / "frame_1.obj").write_text("v 0 0 0\nv 1 0 0\n")
    if case == "unlisted":
        write_raw(source, {"a": 2, "b": 2})
        (source / "split.json").write_text(json.dumps({"train": ["a"], "test": []}))
    argv = ["--data", "aist", "--from", str(source), "--root", str(root), "--points", "10"]
    assert prepare_main(argv) == 2
    err = capsys.readouterr().err
    assert re.search(match, err) and len(err.strip().splitlines()) == 1
    assert not (root / "meta.json").exists()


def test_argument_errors(tmp_path, capsys):
    assert prepare_main(["--data", "dfaust", "--root", str(tmp_path)]) == 2
    assert "needs --from DIR" in capsys.readouterr().err
    assert prepare_main(["--data", "synth-hand", "--from", str(tmp_path)]) == 2
    assert prepare_main(["--data", "dfaust", "--from", str(tmp_path), "--frames", "1"]) == 2
    assert prepare_main(["--data", "nope"]) == 2
    assert "unknown dataset 'nope'" in capsys.readouterr().err


def test_synthetic_calls_the_generator(tmp_path, monkeypatch):
    calls = []

    def generate(name, root, **kwargs):
        calls.append((name, Path(root), kwargs))
        (Path(root) / "meta.json").parent.mkdir(parents=True, exist_ok=True)
        (Path(root) / "meta.json").write_text("{}")
        return Path(root)

    fake = types.SimpleNamespace(generate=generate)
    monkeypatch.setitem(sys.modules, "nmjax.data.synthetic", fake)
    import nmjax.data

    monkeypatch.setattr(nmjax.data, "synthetic", fake, raising=False)
    monkeypatch.setenv("NMJAX_DATA", str(tmp_path))
    argv = ["--data", "synth-quadruped", "--sequences", "2", "--frames", "5", "--seed", "7"]
    assert prepare_main(argv) == 0
    expected = {"num_sequences": 2, "frames": 5, "points": 20_000, "seed": 7}
    assert calls == [("synth-quadruped", tmp_path / "synth-quadruped", expected)]
