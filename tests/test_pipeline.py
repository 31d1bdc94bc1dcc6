"""nmjax.data.pipeline: batch shapes and contents, determinism, resumable iterator state."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from nmjax.config import DataConfig
from nmjax.data import pipeline
from nmjax.data.normalize import normalize_sequence
from nmjax.data.voxelize import voxelize

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
    batch = next(pipeline.skel_iterator(data))
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
    first = pipeline.skel_iterator(data, seed=3)
    second = pipeline.skel_iterator(data, seed=3)
    other = pipeline.skel_iterator(data, seed=4)
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
    batch = next(pipeline.skel_iterator(cfg))
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


def test_augment_crop_is_a_rigid_turn_and_a_shrink():
    rng = np.random.default_rng(3)
    points = rng.normal(size=(4, 30, 3)) * [1.0, 2.0, 0.5]
    joints = rng.normal(size=(4, 5, 3))
    aug = pipeline.Augmentation(rotate_degrees=90.0, scale_jitter=0.3, up_axis=2)
    out, out_joints = pipeline.augment_crop(points, joints, np.random.default_rng(7), aug)
    assert out.dtype == np.float32 and np.all(out >= -1.0) and np.all(out < 1.0)
    # Distances shrink by one factor s in [0.7, 1] (the normalisation's and the jitter's scale
    # together), heights keep their order, and the joints went through the same map.
    before = np.concatenate([points, joints], axis=1)
    after = np.concatenate([out, out_joints], axis=1).astype(np.float64)
    d0 = np.linalg.norm(before[:, :, None] - before[:, None], axis=-1)
    d1 = np.linalg.norm(after[:, :, None] - after[:, None], axis=-1)
    ratio = d1[d0 > 0] / d0[d0 > 0]
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-4)
    np.testing.assert_allclose(
        np.argsort(after[..., 2].ravel()), np.argsort(before[..., 2].ravel())
    )
    # Not the plain normalisation: the crop was turned (the xy-extents changed).
    plain, _ = normalize_sequence(points, joints)
    assert not np.allclose(plain, out, atol=1e-3)


def test_augment_crop_draws_cover_the_ranges():
    points = np.random.default_rng(0).normal(size=(2, 50, 3))
    aug = pipeline.Augmentation(rotate_degrees=30.0, scale_jitter=0.2, up_axis=0)
    angles, scales = [], []
    for seed in range(200):
        out, _ = pipeline.augment_crop(points, None, np.random.default_rng(seed), aug)
        scales.append((out.max(axis=(0, 1)) - out.min(axis=(0, 1))).max() / 2.0)
        # x (the up axis here) is untouched by the turn: its extent is the longest side's share.
        centred = out - out.reshape(-1, 3).mean(axis=0)
        ref = points - points.reshape(-1, 3).mean(axis=0)
        a = np.arctan2(centred[..., 2], centred[..., 1]) - np.arctan2(ref[..., 2], ref[..., 1])
        angles.append(np.rad2deg(np.angle(np.exp(1j * a)).mean()))
    scales, angles = np.array(scales), np.array(angles)
    assert 0.8 - 1e-4 <= scales.min() < 0.82 and 0.98 < scales.max() <= 1.0
    assert -30.5 < angles.min() < -25 and 25 < angles.max() < 30.5


def test_augmentation_only_for_training_crops(data):
    aug = DataConfig(**{**data.__dict__, "rotate_degrees": 180.0, "scale_jitter": 0.5})
    train_plain, train_aug = next(pipeline.skel_iterator(data)), next(pipeline.skel_iterator(aug))
    assert not np.array_equal(train_plain["voxels"], train_aug["voxels"])
    # The draws come after the crop's start: the same sequences and frames, turned.
    assert train_aug["joints"].shape == train_plain["joints"].shape
    plain_eval, aug_eval = (
        pipeline.eval_batches(data, "test", 2),
        pipeline.eval_batches(aug, "test", 2),
    )
    assert all(same(a, b) for a, b in zip(plain_eval, aug_eval, strict=True))
    # Deterministic for the seed, like the plain stream.
    assert same(next(pipeline.skel_iterator(aug)), train_aug)


@pytest.mark.parametrize(
    "field, value", [("rotate_degrees", 200.0), ("scale_jitter", 1.0), ("up_axis", 3)]
)
def test_bad_augmentation_is_named(data, field, value):
    bad = DataConfig(**{**data.__dict__, field: value})
    with pytest.raises(ValueError, match=f"data.{field}"):
        next(pipeline.skel_iterator(bad))
