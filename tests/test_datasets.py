"""nmjax.data.datasets and .layout on tiny datasets written by the tests: layout, splits, crops,
bad input."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from nmjax.data import layout
from nmjax.data.datasets import (
    Sequence,
    crop_indices,
    crop_sequence,
    load_sequences,
    sample_start,
)
from nmjax.data.layout import dataset_root, split_by_frames


def write_sequence(
    root: Path,
    split: str | None,
    seq: str,
    frames: int,
    points: int = 8,
    joints: int | None = 3,
    joint_name: str | None = None,
    seed: int = 0,
):
    """Writes one sequence whose point t, n is (t, n, seed) + noise; returns (vertices, joints)."""
    rng = np.random.default_rng(seed)
    base = root if split is None else root / split
    t = np.arange(frames, dtype=np.float32)[:, None, None]
    vertices = (t + rng.normal(size=(frames, points, 3))).astype(np.float32)
    (base / "vertices").mkdir(parents=True, exist_ok=True)
    np.save(base / "vertices" / f"{seq}.npy", vertices)
    gt = None
    if joints is not None:
        gt = (t + rng.normal(size=(frames, joints, 3))).astype(np.float32)
        (base / "joints").mkdir(parents=True, exist_ok=True)
        np.save(base / "joints" / (joint_name or f"{seq}.npy"), gt)
    return vertices, gt


@pytest.fixture
def presplit(tmp_path):
    root = tmp_path / "dfaust"
    arrays = {}
    for split, names in {"train": ["b", "a", "c"], "test": ["d"]}.items():
        for i, seq in enumerate(names):
            arrays[seq] = write_sequence(root, split, seq, frames=4 + i, seed=i)
    return root, arrays


def test_presplit_layout(presplit):
    root, arrays = presplit
    train = load_sequences("dfaust", "train", root)
    assert [s.name for s in train] == ["a", "b", "c"]
    for s in train:
        assert isinstance(s, Sequence)
        assert s.vertices.dtype == np.float32 and isinstance(s.vertices, np.memmap)
        np.testing.assert_array_equal(s.vertices, arrays[s.name][0])
        np.testing.assert_array_equal(s.joints, arrays[s.name][1])
        assert s.path == root / "train" / "vertices" / f"{s.name}.npy"
        assert s.joints_path == root / "train" / "joints" / f"{s.name}.npy"
    assert [s.name for s in load_sequences("dfaust", "test", root)] == ["d"]


def test_hanco_joint_names_and_float64(tmp_path):
    root = tmp_path / "hanco"
    vertices, joints = write_sequence(root, "train", "0007", 3, joint_name="0007_joints.npy")
    np.save(root / "train" / "vertices" / "0007.npy", vertices.astype(np.float64))
    (seq,) = load_sequences("hanco", "train", root)
    assert seq.vertices.dtype == np.float32
    np.testing.assert_array_equal(seq.vertices, vertices)
    np.testing.assert_array_equal(seq.joints, joints)
    assert seq.joints_path.name == "0007_joints.npy"


def test_sequence_without_joints(tmp_path):
    root = tmp_path / "animals"
    write_sequence(root, "train", "x", 3, joints=None)
    (seq,) = load_sequences("animals", "train", root)
    assert seq.joints is None and seq.joints_path is None


def test_split_file_decides(presplit):
    root, _ = presplit
    (root / "split.json").write_text(json.dumps({"train": ["d", "a"], "test": ["b", "c"]}))
    assert [s.name for s in load_sequences("dfaust", "train", root)] == ["a", "d"]
    assert [s.name for s in load_sequences("dfaust", "test", root)] == ["b", "c"]
    (root / "split.json").write_text(json.dumps({"train": ["a", "zz"], "test": []}))
    with pytest.raises(ValueError, match="zz"):
        load_sequences("dfaust", "train", root)
    (root / "split.json").write_text(json.dumps({"train": "a"}))
    with pytest.raises(ValueError, match="split.json"):
        load_sequences("dfaust", "train", root)


def test_unsplit_pool_is_divided_nine_to_one(tmp_path):
    root = tmp_path / "aist"
    for i in range(10):
        write_sequence(root, None, f"s{i}", frames=10, points=2, joints=None)
    train = {s.name for s in load_sequences("aist", "train", root)}
    test = {s.name for s in load_sequences("aist", "test", root)}
    assert len(test) == 1 and len(train) == 9 and not train & test
    assert train | test == {f"s{i}" for i in range(10)}


def test_split_by_frames():
    counts = {f"seq{i:02d}": 10 + 7 * i for i in range(12)}
    split = split_by_frames(counts)
    assert split == split_by_frames(dict(reversed(counts.items())))  # order-independent
    assert sorted(split["train"] + split["test"]) == sorted(counts)
    held = sum(counts[s] for s in split["test"])
    total = sum(counts.values())
    assert held >= 0.1 * total
    # Minimal: sequences join the test split in sha256 order of their names, and without the
    # last one to join it would hold under 10% of the frames.
    last = max(split["test"], key=lambda s: hashlib.sha256(s.encode()).hexdigest())
    assert held - counts[last] < 0.1 * total
    first_train = min(split["train"], key=lambda s: hashlib.sha256(s.encode()).hexdigest())
    assert (
        hashlib.sha256(first_train.encode()).hexdigest() > hashlib.sha256(last.encode()).hexdigest()
    )
    assert split_by_frames({"only": 50}) == {"train": ["only"], "test": []}
    two = split_by_frames({"a": 5, "b": 5})
    assert len(two["train"]) == 1 and len(two["test"]) == 1


def test_dataset_root(monkeypatch, tmp_path):
    monkeypatch.delenv("NMJAX_DATA", raising=False)
    assert dataset_root("hanco") == Path("data") / "hanco"
    assert dataset_root("hanco", tmp_path) == tmp_path
    monkeypatch.setenv("NMJAX_DATA", str(tmp_path))
    assert dataset_root("panda") == tmp_path / "panda"
    with pytest.raises(ValueError, match="unknown dataset 'nope'.*synth-hand"):
        dataset_root("nope")


def test_missing_folder_message(tmp_path):
    folder = tmp_path / "nowhere"
    with pytest.raises(FileNotFoundError) as err:
        load_sequences("dfaust", "train", folder)
    message = str(err.value)
    assert str(folder) in message
    assert "nmjax prepare-data --data dfaust --from DIR" in message
    assert "DATA=synth-hand" in message
    folder.mkdir()
    with pytest.raises(FileNotFoundError, match="sequence folder"):
        load_sequences("dfaust", "train", folder)
    with pytest.raises(ValueError, match="split must be"):
        load_sequences("dfaust", "val", folder)


def test_empty_split_is_an_error(tmp_path):
    root = tmp_path / "panda"
    write_sequence(root, "train", "a", 3)
    with pytest.raises(ValueError, match="no 'test' sequences"):
        load_sequences("panda", "test", root)


BAD_VERTICES = {
    "rank": (np.zeros((4, 3), np.float32), r"shape \(T, N, 3\)"),
    "last-axis": (np.zeros((4, 5, 2), np.float32), r"shape \(T, N, 3\)"),
    "nan": (np.where(np.arange(60).reshape(4, 5, 3) == 31, np.nan, 0.0), "NaN, inf.*frame 2"),
    "inf": (np.full((3, 5, 3), np.inf, np.float32), "NaN, inf"),
    # Finite in float64, inf once loaded as float32: refused, not turned into inf.
    "beyond-float32": (np.full((3, 5, 3), 1e300), "beyond the float32 range"),
    "empty-frames": (np.zeros((4, 0, 3), np.float32), "empty frames"),
    "one-frame": (np.zeros((1, 5, 3), np.float32), "at least 2 frames"),
    "integers": (np.zeros((3, 5, 3), np.int32), "floating point"),
}


@pytest.mark.parametrize("case", sorted(BAD_VERTICES))
def test_bad_vertices(tmp_path, case):
    array, match = BAD_VERTICES[case]
    root = tmp_path / "dfaust"
    (root / "train" / "vertices").mkdir(parents=True)
    path = root / "train" / "vertices" / "bad.npy"
    np.save(path, array)
    with pytest.raises(ValueError, match=match) as err:
        load_sequences("dfaust", "train", root)
    assert str(path) in str(err.value)


def test_unreadable_file(tmp_path):
    root = tmp_path / "dfaust"
    (root / "train" / "vertices").mkdir(parents=True)
    path = root / "train" / "vertices" / "torn.npy"
    path.write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(ValueError, match="not a readable .npy") as err:
        load_sequences("dfaust", "train", root)
    assert str(path) in str(err.value)


@pytest.mark.parametrize(
    "joints, match",
    [
        (np.zeros((5, 3, 3), np.float32), "5 joint frames but the vertices file has 4"),
        (np.zeros((4, 3), np.float32), r"shape \(T, J, 3\)"),
        (np.full((4, 3, 3), np.nan, np.float32), "joints contain NaN"),
    ],
)
def test_bad_joints(tmp_path, joints, match):
    root = tmp_path / "dfaust"
    write_sequence(root, "train", "a", 4, joints=None)
    (root / "train" / "joints").mkdir()
    path = root / "train" / "joints" / "a.npy"
    np.save(path, joints)
    with pytest.raises(ValueError, match=match) as err:
        load_sequences("dfaust", "train", root)
    assert str(path) in str(err.value)


def test_a_missing_synthetic_set_is_an_error_naming_the_command(tmp_path, monkeypatch):
    monkeypatch.setenv("NMJAX_DATA", str(tmp_path))
    with pytest.raises(FileNotFoundError) as err:
        load_sequences("synth-arm", "train")
    root = tmp_path / "synth-arm"
    assert f"nmjax prepare-data --data synth-arm --root {root}" in str(err.value)
    assert "ensure_dataset" in str(err.value)
    assert not root.exists()  # the loader does not generate it


def test_a_synthetic_set_loads_once_its_meta_marks_it_complete(tmp_path, monkeypatch):
    monkeypatch.setenv("NMJAX_DATA", str(tmp_path))
    root = tmp_path / "synth-arm"
    write_sequence(root, "train", "s0", 3)
    write_sequence(root, "test", "s1", 3)
    with pytest.raises(FileNotFoundError, match=r"--root .*synth-arm --overwrite"):
        load_sequences("synth-arm", "train")
    (root / "meta.json").write_text(json.dumps({"name": "synth-arm", "complete": True}))
    assert [s.name for s in load_sequences("synth-arm", "train")] == ["s0"]
    assert [s.name for s in load_sequences("synth-arm", "test")] == ["s1"]
    assert layout.read_meta("synth-arm") == {"name": "synth-arm", "complete": True}


def test_crop_indices_rate_and_padding():
    np.testing.assert_array_equal(crop_indices(20, 4, 3, 5), [5, 8, 11, 14])
    np.testing.assert_array_equal(crop_indices(7, 4, 2, 3), [3, 5, 6, 6])  # padded with last
    np.testing.assert_array_equal(crop_indices(2, 3, 1, 0), [0, 1, 1])
    with pytest.raises(ValueError, match="outside"):
        crop_indices(5, 2, 1, 5)


def test_crop_sequence(tmp_path):
    root = tmp_path / "dfaust"
    vertices, joints = write_sequence(root, "train", "a", 6)
    (seq,) = load_sequences("dfaust", "train", root)
    v, j = crop_sequence(seq, frames=4, sample_rate=2, start=1)
    np.testing.assert_array_equal(v, vertices[[1, 3, 5, 5]])
    np.testing.assert_array_equal(j, joints[[1, 3, 5, 5]])
    assert type(v) is np.ndarray and v.dtype == np.float32


def test_sample_start_covers_every_fitting_start():
    rng = np.random.default_rng(0)
    starts = {sample_start(rng, num_frames=12, frames=4, sample_rate=2) for _ in range(400)}
    assert starts == set(range(12 - 7 + 1))  # span (4 - 1) * 2 + 1 = 7
    assert {sample_start(rng, 5, 4, 2) for _ in range(20)} == {0}  # too short: from the start
