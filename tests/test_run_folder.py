"""Tests of nmjax.run_folder (what a run folder holds, written and read in one place) and of the
configuration's shared groups as config.json stores them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nmjax import run_folder
from nmjax.config import DynTrainConfig, SkelTrainConfig, dyn_preset, skel_preset
from nmjax.config_io import apply_overrides, config_from_dict, config_to_dict, replace_fields
from nmjax.skeleton import skeleton_from_parents


def _flat(config) -> dict:
    """`config` as a config.json of the time before the shared groups: their fields top-level."""
    nested = config_to_dict(config)
    optim, loop = nested.pop("optim"), nested.pop("loop")
    return {**nested, **optim, **loop}


def test_a_flat_config_json_reads_into_the_nested_groups(tmp_path):
    skel = replace_fields(skel_preset("synth-arm", "cpu"), steps=123, clip_norm=0.5)
    (tmp_path / "skel").mkdir()
    (tmp_path / "skel" / run_folder.CONFIG_FILE).write_text(json.dumps(_flat(skel)))
    assert run_folder.load_config(tmp_path / "skel", SkelTrainConfig) == skel
    # A phase-2 file of that time had no decay epochs, weight average or time limit: they read
    # as phase 2's defaults, not phase 1's (no decays in a 150-epoch run).
    old_dyn = _flat(dyn_preset("synth-arm"))
    for name in ("decay_epochs", "lr_milestones", "lr_decay", "ema_decay", "time_limit_minutes"):
        old_dyn.pop(name)
    old_dyn["steps"] = 7
    dyn = config_from_dict(DynTrainConfig, old_dyn)
    assert dyn == replace_fields(dyn_preset("synth-arm"), steps=7)
    assert (dyn.optim.decay_epochs, dyn.loop.epochs) == ((), 150)
    with pytest.raises(ValueError, match="bogus"):
        config_from_dict(DynTrainConfig, {**old_dyn, "bogus": 1})


def test_overrides_take_bare_and_dotted_names_of_the_shared_groups():
    cfg = skel_preset("synth-arm", "tiny")
    bare = apply_overrides(cfg, ["steps=9", "learning_rate=0.01", "lr_milestones=3,7"])
    dotted = apply_overrides(cfg, ["loop.steps=9", "optim.learning_rate=0.01"])
    dotted = apply_overrides(dotted, ["optim.lr_milestones=3,7"])
    assert bare == dotted == replace_fields(cfg, steps=9, learning_rate=0.01, lr_milestones=(3, 7))
    assert (bare.loop.steps, bare.optim.learning_rate, bare.optim.lr_milestones) == (
        9,
        0.01,
        (3, 7),
    )
    with pytest.raises(ValueError, match="no field 'nope'"):
        apply_overrides(cfg, ["nope=1"])


def test_phase1_artifacts_written_are_what_the_readers_give_back(tmp_path):
    rng = np.random.default_rng(0)
    affinity = rng.uniform(size=(2, 5, 5))
    keypoints = rng.uniform(size=(3, 2, 4, 5, 4))  # (batches, B, T, K, 4)
    voxels = (rng.uniform(size=(8, 8, 8)) > 0.5).astype(np.float32)
    run_folder.write_phase1_artifacts(tmp_path, affinity, keypoints, voxels)
    read_affinity, stats = run_folder.read_skeleton_inputs(tmp_path)
    flat = keypoints.reshape(-1, 5, 4).astype(np.float32)
    np.testing.assert_allclose(read_affinity, affinity, rtol=1e-6)
    np.testing.assert_allclose(stats["intensities"], flat[:, :, 3].mean(0), rtol=1e-6)
    np.testing.assert_allclose(stats["rest_positions"], flat[:, :, :3].mean(0), rtol=1e-6)
    np.testing.assert_array_equal(stats["example_voxels"], voxels)
    np.testing.assert_array_equal(stats["example_keypoints"], keypoints[0, 0, 0].astype(np.float32))
    assert sorted(stats) == sorted(run_folder.STATS_KEYS)

    tree = skeleton_from_parents((0, 0, 1, 1, 3), (0, 1, 3, 2, 4))
    run_folder.write_skeleton(tmp_path, tree, intensities=np.full(5, 0.5), keep=[True] * 5)
    assert run_folder.read_skeleton(tmp_path) == tree
    np.testing.assert_array_equal(run_folder.skeleton_intensities(tmp_path), np.full(5, 0.5))
    motion = {"a": rng.normal(size=(6, 5, 4)), "b": rng.normal(size=(3, 5, 4))}
    run_folder.write_trajectories(run_folder.keypoints_file(tmp_path, "test"), motion)
    back = run_folder.load_trajectories(tmp_path, "test")
    assert sorted(back) == ["a", "b"] and back["a"].dtype == np.float32
    np.testing.assert_allclose(back["b"], motion["b"], rtol=1e-6)


def test_a_new_run_is_named_so_that_the_latest_phase1_run_is_found(tmp_path, monkeypatch):
    monkeypatch.setattr(run_folder, "RUNS_ROOT", tmp_path)
    skel = run_folder.default_run_dir("skel", "synth-arm")
    dyn = run_folder.default_run_dir("dyn", "synth-arm", "vrnn")
    assert skel.parent == tmp_path and skel.name.startswith("skel-synth-arm-")
    assert dyn.name.startswith("dyn-synth-arm-vrnn-")
    older = tmp_path / "skel-synth-arm-20000101-000000"
    older.mkdir()
    skel.mkdir()
    assert run_folder.find_skel_run("synth-arm", runs_root=tmp_path) == skel


def test_a_used_folder_is_refused_unless_resumed_or_overwritten(tmp_path):
    cfg = skel_preset("synth-arm", "tiny")
    run = run_folder.prepare_run_dir(tmp_path / "run", resume=False, config=cfg)
    (run / "leftover").write_text("x")
    with pytest.raises(ValueError, match="already exists"):
        run_folder.check_run_dir(run, resume=False, config=cfg)
    with pytest.raises(FileNotFoundError, match="no complete checkpoint"):
        run_folder.check_run_dir(run, resume=True, config=cfg)
    # Resuming may change the loop's length and cadence, nothing else.
    (run_folder.checkpoint_dir(run) / "2").mkdir(parents=True)
    run_folder.check_run_dir(run, resume=True, config=replace_fields(cfg, steps=40, log_every=1))
    with pytest.raises(ValueError, match="optim.learning_rate"):
        run_folder.check_run_dir(run, resume=True, config=replace_fields(cfg, learning_rate=1.0))
    run_folder.prepare_run_dir(run, resume=False, config=cfg, overwrite=True)
    assert sorted(p.name for p in run.iterdir()) == [run_folder.CONFIG_FILE]
