"""The two phases' entry points, `skel.train_skeleton` and `dyn.train_dynamics`, shaped alike: the
run folder from the config, the same refusal of a used folder, the epochs counted by one rule,
the same summary; and the one checkpoint that phase 1's artefacts and every reader take."""

from __future__ import annotations

import dataclasses
import inspect
import math

import jax.numpy as jnp
import numpy as np
import pytest
from tiny_configs import fake_run_dyn_config, short_skel_config, small_skel_config

from nmjax import config, run_folder
from nmjax.config_io import replace_fields
from nmjax.data.datasets import load_sequences
from nmjax.train import checkpoints, dyn, loop, skel, trained

ENTRIES = (skel.train_skeleton, dyn.train_dynamics)


def test_both_entries_take_the_same_keywords():
    shapes = [
        [(p.name, p.kind, p.default) for p in inspect.signature(entry).parameters.values()]
        for entry in ENTRIES
    ]
    common = ["cfg", "resume", "overwrite", "progress", "step_hook"]
    for shape in shapes:
        assert [name for name, _, _ in shape][: len(common)] == common
    # Phase 1 alone may skip its closing artefacts; every shared keyword reads the same.
    assert shapes[0][: len(common)] == shapes[1][: len(common)]
    assert [name for name, _, _ in shapes[0][len(common) :]] == ["finalize"]


def _phase1(data_root, run, **changes):
    return small_skel_config(
        data_root, run=str(run), steps=2, log_every=1, val_every=2, ckpt_every=2, **changes
    )


def _phase2(fake_run, run, **changes):
    return fake_run_dyn_config(fake_run, run, steps=2, log_every=1, val_every=2, **changes)


def test_both_refuse_a_used_run_folder_alike_and_overwrite_it_when_asked(
    data_root, fake_run, tmp_path
):
    messages = []
    for entry, cfg in (
        (skel.train_skeleton, _phase1(data_root, tmp_path / "skel", val_batches=1)),
        (dyn.train_dynamics, _phase2(fake_run, tmp_path / "dyn")),
    ):
        first = entry(cfg, progress=False)
        with pytest.raises(ValueError, match="already exists") as refused:
            entry(cfg, progress=False)
        messages.append(str(refused.value).replace(str(first.run), "RUN"))
        again = entry(cfg, overwrite=True, progress=False)
        # Replaced, not continued: the new run starts at step 0.
        assert again.run == first.run and again.start_step == 0 and again.step == 2
        assert isinstance(first, loop.TrainSummary) and isinstance(again, loop.TrainSummary)
        fields = {f.name for f in dataclasses.fields(first)}
        assert fields == {"run", "start_step", "step", "stop_reason", "validation"}
        assert first.stop_reason == "steps" and first.validation
        assert all(k.startswith("val/") for k in first.validation)
    assert messages[0] == messages[1]  # one rule, one wording


def test_both_count_epochs_by_the_one_rule(data_root, fake_run, tmp_path):
    # The tiny synth-arm set has 1 training sequence, the fake phase-1 run 3; B = 2 in phase 2.
    cases = (
        (skel.train_skeleton, _phase1(data_root, tmp_path / "skel", val_batches=1), 2, 1, 1),
        (dyn.train_dynamics, _phase2(fake_run, tmp_path / "dyn", batch_size=2), 1, 3, 2),
    )
    for entry, cfg, epochs, sequences, batch in cases:
        # Counted in epochs, without decays (the tiny runs are shorter than any preset's).
        cfg = replace_fields(cfg, epochs=epochs, decay_epochs=(), lr_milestones=())
        summary = entry(replace_fields(cfg, val_every=100), progress=False)
        saved = run_folder.load_config(summary.run, type(cfg))
        expected = config.resolve_epochs(cfg, sequences, batch).loop
        assert saved.loop.steps_per_epoch == math.ceil(sequences / batch)
        assert saved.loop.steps == cfg.loop.epochs * saved.loop.steps_per_epoch
        assert dataclasses.replace(saved.loop, val_every=cfg.loop.val_every) == expected
        assert summary.step == saved.loop.steps


def test_exported_keypoints_and_the_skeleton_come_from_the_detector_every_reader_loads(
    data_root, tmp_path, monkeypatch
):
    # Validation is made to rank step 1 best, so the best checkpoint is not the last (step 3).
    validate = skel.validate
    calls = []

    def first_is_best(*args, **kwargs):
        scalars, keypoints = validate(*args, **kwargs)
        calls.append(None)
        return {**scalars, "val/loss": scalars["val/loss"] + 1e3 * (len(calls) > 1)}, keypoints

    monkeypatch.setattr(skel, "validate", first_is_best)
    run = tmp_path / "skel"
    cfg = short_skel_config(data_root, run=str(run), steps=3, val_every=1, lr_milestones=())
    skel.train_skeleton(cfg, progress=False)
    with checkpoints.Checkpointer(
        run_folder.checkpoint_dir(run), cfg.loop.keep_checkpoints, skel.BEST_METRIC
    ) as ckpt:
        assert (ckpt.best_step(), ckpt.latest_step()) == (1, 3)

    detector = trained.Detector.load(run)
    (name, exported), *_ = run_folder.load_trajectories(run, "test").items()
    (seq,) = (s for s in load_sequences(cfg.data.name, "test", cfg.data.root) if s.name == name)
    voxels = trained.sequence_voxels(seq, cfg.data.sample_rate, cfg.data.grid)
    windows = trained.sequence_windows(voxels, cfg.data.frames)
    for step, same in ((None, True), (3, False)):
        model = detector if step is None else trained.Detector.load(run, step)
        keypoints = model.keypoints(windows).reshape(-1, *exported.shape[1:])[: len(exported)]
        assert np.allclose(keypoints, exported, atol=1e-6) is same
        affinity = np.asarray(
            trained.restore_detector(run, step)[0].affinity(), np.float32
        )  # the affinity skeleton.json was extracted from
        assert np.allclose(np.load(run / run_folder.AFFINITY_FILE), affinity, atol=1e-6) is same
    assert bool(jnp.all(jnp.isfinite(exported)))
