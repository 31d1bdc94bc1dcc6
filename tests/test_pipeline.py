"""nmjax.data.pipeline: batch shapes and contents, determinism, resumable iterator state."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from nmjax.config import DataConfig
from nmjax.data import pipeline
from nmjax.data.voxelize import normalize_sequence, voxelize

GRID = 8


def make_dataset(root: Path, lengths: dict[str, dict[str, int]], joints: bool = True) -> Path:
    rng = np.random.default_rng(0)
    for split, seqs in lengths.items():
        for seq, frames in seqs.items():
            (root / split / "vertices").mkdir(parents=True, exist_ok=True)
            vertices = rng.normal(size=(frames, 40, 3)) * rng.uniform(0.5, 3.0, size=3)
            np.save(root / split / "vertices" / f"{seq}.npy", vertices.astype(np.float32))
            if joints:
                (root / split / "joints").mkdir(parents=True, exist_ok=True)
                gt = rng.normal(size=(frames, 5, 3)).astype(np.float32)
                np.save(root / split / "joints" / f"{seq}.npy", gt)
    return root


@pytest.fixture
def data(tmp_path):
    lengths = {"train": {"a": 30, "b": 25, "c": 40}, "test": {"d": 20, "e": 12}}
    root = make_dataset(tmp_path / "dfaust", lengths)
    return DataConfig(
        name="dfaust", root=str(root), grid=GRID, frames=4, sample_rate=2, batch_size=2
    )


def same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def test_shapes_and_values(data):
    batch = next(pipeline.skel_batches(data))
    assert batch["voxels"].shape == (2, 4, GRID, GRID, GRID)
    assert batch["voxels"].dtype == np.float32
    assert set(np.unique(batch["voxels"])) <= {0.0, 1.0}
    assert batch["joints"].shape == (2, 4, 5, 3) and batch["joints"].dtype == np.float32
    # Every frame of a 40-point cloud occupies between 1 and 40 cells.
    per_frame = batch["voxels"].sum(axis=(2, 3, 4))
    assert np.all(per_frame >= 1) and np.all(per_frame <= 40)


def test_crops_match_an_independent_computation(tmp_path):
    # Each sequence is exactly one crop long (span (4-1)*2+1 = 7), so the start must be 0 and
    # every batch element equals one sequence's crop, normalised and voxelised here.
    root = make_dataset(tmp_path / "dfaust", {"train": {"a": 7, "b": 7, "c": 3}})
    cfg = DataConfig(name="dfaust", root=str(root), grid=GRID, frames=4, sample_rate=2,
                     batch_size=3)  # fmt: skip
    expected = {}
    for seq in "abc":
        v = np.load(root / "train" / "vertices" / f"{seq}.npy")
        j = np.load(root / "train" / "joints" / f"{seq}.npy")
        idx = [0, 2, 4, 6] if len(v) == 7 else [0, 2, 2, 2]  # "c" is padded with its last frame
        pts, jts = normalize_sequence(v[idx], j[idx])
        expected[seq] = (voxelize(pts, GRID), jts)
    batches = pipeline.eval_batches(cfg, "train", num_batches=2)
    for batch in batches:
        found = set()
        for voxels, joints in zip(batch["voxels"], batch["joints"], strict=True):
            match = [s for s, (ev, ej) in expected.items() if np.array_equal(voxels, ev)]
            assert len(match) == 1
            np.testing.assert_allclose(joints, expected[match[0]][1], atol=1e-6)
            found.add(match[0])
        assert found == {"a", "b", "c"}  # one epoch per batch: each sequence once
    # The padded sequence repeats its last frame.
    c = expected["c"][0]
    np.testing.assert_array_equal(c[1], c[3])


def test_deterministic_for_a_seed(data):
    first = pipeline.skel_batches(data, seed=3)
    second = pipeline.skel_batches(data, seed=3)
    other = pipeline.skel_batches(data, seed=4)
    a = [next(first) for _ in range(4)]
    b = [next(second) for _ in range(4)]
    c = [next(other) for _ in range(4)]
    assert all(same(x, y) for x, y in zip(a, b, strict=True))
    assert not all(same(x, y) for x, y in zip(a, c, strict=True))
    assert not same(a[0], a[1])


def test_iterator_state_round_trip(data):
    iterator = pipeline.skel_iterator(data, "train", seed=1)
    for _ in range(3):
        next(iterator)
    state = json.loads(json.dumps(iterator.get_state()))  # what a checkpoint stores
    expected = [next(iterator) for _ in range(2)]
    restored = pipeline.skel_iterator(data, "train", seed=1)
    restored.set_state(state)
    assert all(same(x, next(restored)) for x in expected)


def test_grain_checkpoint_handler(data, tmp_path):
    import grain

    iterator = pipeline.skel_iterator(data)
    next(iterator)
    handler = grain.checkpoint.CheckpointHandler()  # what orbax calls inside a checkpoint
    (tmp_path / "ckpt").mkdir()  # orbax creates the item folder before calling the handler
    handler.save(tmp_path / "ckpt", item=iterator)
    expected = next(iterator)
    restored = pipeline.skel_iterator(data)
    handler.restore(tmp_path / "ckpt", item=restored)
    assert same(expected, next(restored))


def test_eval_batches_fixed(data):
    first = pipeline.eval_batches(data, "test", num_batches=3, seed=0)
    second = pipeline.eval_batches(data, "test", num_batches=3, seed=0)
    assert len(first) == 3
    assert all(same(x, y) for x, y in zip(first, second, strict=True))
    with pytest.raises(ValueError, match="num_batches"):
        pipeline.eval_batches(data, "test", num_batches=0)


def test_no_joints_key_without_joints(tmp_path):
    root = make_dataset(tmp_path / "animals", {"train": {"a": 9}}, joints=False)
    cfg = DataConfig(name="animals", root=str(root), grid=GRID, frames=3, batch_size=2)
    batch = next(pipeline.skel_batches(cfg))
    assert set(batch) == {"voxels"} and batch["voxels"].shape == (2, 3, GRID, GRID, GRID)


def test_bad_config(data):
    import dataclasses

    with pytest.raises(ValueError, match="batch_size"):
        pipeline.skel_iterator(dataclasses.replace(data, batch_size=0))
    with pytest.raises(ValueError, match="frames"):
        pipeline.skel_iterator(dataclasses.replace(data, frames=0))


def test_worker_process_gives_the_same_batches(data):
    import dataclasses

    reference = pipeline.skel_iterator(data, seed=2)
    expected = [next(reference) for _ in range(3)]
    iterator = pipeline.skel_iterator(dataclasses.replace(data, worker_count=1), seed=2)
    try:
        assert all(same(x, next(iterator)) for x in expected)
    finally:
        iterator.close()
