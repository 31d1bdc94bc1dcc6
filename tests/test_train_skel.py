"""Tests of phase-1 training (nmjax.train.skel): learning, single compilation, exact resume,
NaN stop, bad input, run-folder artefacts (nmjax.train.trained)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from flax import nnx
from tiny_configs import short_skel_config as _cfg
from tiny_runs import poison_after

from nmjax import config, config_io, run_folder
from nmjax.cli import main as nmjax_main
from nmjax.config import skel_preset
from nmjax.config_io import replace_fields
from nmjax.train import checkpoints, metric_log, parallel, skel, trained


def _leaves(state):
    return [np.asarray(x) for x in jax.tree.leaves(state)]


def _restored_equal(tmp_path, abstract, step):
    """The states of the "straight" and "resumed" runs' checkpoints at `step`, checked equal."""
    restored = {}
    for name in ("straight", "resumed"):
        with checkpoints.Checkpointer(tmp_path / name / "checkpoints", keep=3) as ckpt:
            restored[name] = ckpt.restore(abstract, step=step)[1]
    for a, b in zip(_leaves(restored["straight"]), _leaves(restored["resumed"]), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    return restored


def test_loss_decreases_on_fixed_batch_and_compiles_once(data_root, monkeypatch):
    from nmjax.data import pipeline

    # Traced at most once over all the steps (zero times if another test compiled this step).
    monkeypatch.setattr(skel, "loss_fn", chex.assert_max_traces(skel.loss_fn, n=1))
    cfg = _cfg(data_root, learning_rate=1e-2)
    graphdef, state = skel.build(cfg)
    mesh = parallel.data_mesh()
    state = parallel.replicate(state, mesh)  # placed as the trainer places it
    step_fn, _ = skel.make_steps(graphdef, cfg, mesh)
    batch = skel.device_batch(next(pipeline.skel_iterator(cfg.data, "train")), cfg, mesh)
    losses = []
    for _ in range(12):
        state, scalars = step_fn(state, batch)
        losses.append(float(scalars["loss"]))
    # The released initialisation starts every layer small (the decoder's output near its copy
    # of v_1), so the loss falls steadily but by a few percent in the first steps.
    assert all(b < a for a, b in zip(losses[2:], losses[3:], strict=False)), losses
    assert losses[-1] < 0.97 * losses[0], losses
    assert set(scalars) >= {"loss", "recon", "sparse", "sep", "vol", "local", "time", "traj"}


@pytest.fixture(scope="module")
def three_sequences(tmp_path_factory):
    """synth-arm with 2 training sequences and 1 test sequence: 2 steps an epoch at B = 1."""
    from nmjax.data import synthetic

    root = tmp_path_factory.mktemp("data3") / "synth-arm"
    return synthetic.generate(
        "synth-arm", root, num_sequences=3, frames=8, points=2000, progress=False
    )


def test_resume_equals_straight_run_and_writes_artifacts(three_sequences, tmp_path, monkeypatch):
    # The compiled step is shared by the three runs of this process: at most one trace.
    monkeypatch.setattr(skel, "loss_fn", chex.assert_max_traces(skel.loss_fn, n=1))
    cfg = _cfg(three_sequences)
    straight = skel.train_skeleton(
        replace_fields(cfg, run=str(tmp_path / "straight")), progress=False
    )
    first = skel.train_skeleton(
        replace_fields(cfg, steps=3, run=str(tmp_path / "resumed")),
        progress=False,
        finalize=False,
    )
    assert first.step == 3
    resumed = skel.train_skeleton(
        replace_fields(cfg, run=str(tmp_path / "resumed")),
        resume=True,
        progress=False,
        finalize=False,
    )
    assert resumed.start_step == 3 and resumed.step == 6
    # The state as the trainer built it: with the epochs resolved (2 sequences at B = 1).
    graphdef, state = skel.build(config.resolve_epochs(cfg, 2, 1))
    _restored_equal(tmp_path, skel.abstract_state(state), step=6)
    assert straight.validation["val/loss"] == pytest.approx(
        resumed.validation["val/loss"], rel=1e-5
    )
    # The resumed run's log reads like the straight one's: each step once, in order.
    records = metric_log.read_metrics(tmp_path / "resumed")
    train_steps = [r["step"] for r in records if "train/loss" in r]
    assert train_steps == [1, 2, 3, 4, 5, 6]
    # The fusion weights ride with the training scalars (they start near 0, the bias at 0, and
    # move with the steps), the heatmaps' far mass with the validation ones.
    first_log = next(r for r in records if "train/loss" in r)
    assert first_log["train/fuse_b"] != 0.0
    assert abs(first_log["train/fuse_w_frame"]) < 0.1 and abs(first_log["train/fuse_w_st"]) < 0.1
    assert 0.0 < straight.validation["val/heat_far_mass"] < 1.0
    # Adam restarted at the epoch boundaries (2 training sequences at B = 1: steps 2 and 4), so
    # the resumed run crossed one (step 4) after it resumed at step 3, and matched regardless.
    saved = json.loads((tmp_path / "resumed" / "config.json").read_text())
    assert saved["optim"]["optimizer_reset"] == "epoch" and saved["loop"]["steps_per_epoch"] == 2

    run = tmp_path / "straight"
    k, n, g = cfg.model.num_keypoints, cfg.model.num_affinity, cfg.model.grid
    affinity = np.load(run / "affinity.npy")
    assert affinity.shape == (n, k, k) and affinity.dtype == np.float32
    np.testing.assert_allclose(affinity.sum(-1), 1.0, atol=1e-5)
    stats = np.load(run / "keypoint_stats.npz")
    assert sorted(stats.files) == sorted(run_folder.STATS_KEYS)  # what nmjax.train.trained reads
    assert stats["intensities"].shape == (k,)
    assert stats["rest_positions"].shape == (k, 3)
    assert stats["example_voxels"].shape == (g, g, g)
    assert stats["example_keypoints"].shape == (k, 4)
    skeleton = json.loads((run / "skeleton.json").read_text())
    assert len(skeleton["parents"]) == k
    assert (
        "val/sc_score" in straight.validation and 0.0 < straight.validation["val/sc_score"] <= 1.0
    )
    assert 0.0 < straight.validation["val/sc_fixed_nodes"] <= 1.0
    assert list((run / "figures").glob("keypoints_*.png"))
    assert list((run / "tb").iterdir())
    saved = json.loads((run / "config.json").read_text())
    assert saved["model"]["channels"] == 4 and saved["loop"]["steps"] == 6
    for split, count in (("train", 2), ("test", 1)):
        with np.load(run / f"keypoints_{split}.npz") as archive:
            assert len(archive.files) == count
            kp = archive[archive.files[0]]
            assert kp.shape == (8, k, 4)  # the whole 8-frame sequence, windows of T=3 padded
    # The exported values are the best checkpoint's detector's keypoints, window by window (the
    # last window padded with the last frame), computed here without the exporter's batching.
    from nmjax.data.datasets import load_sequences

    model, _ = trained.restore_detector(run)
    (seq,) = load_sequences(cfg.data.name, "test", cfg.data.root)
    windows = trained.sequence_windows(trained.sequence_voxels(seq, cfg.data.sample_rate, 8), 3)
    direct = np.concatenate([np.asarray(model.detect(jnp.asarray(w[None]))[1][0]) for w in windows])
    with np.load(run / "keypoints_test.npz") as archive:
        np.testing.assert_allclose(archive[seq.name], direct[:8], rtol=1e-5, atol=1e-6)


def test_weight_average_resumes_exactly_and_is_the_exported_detector(data_root, tmp_path):
    cfg = _cfg(data_root, ema_decay=0.5)
    straight = skel.train_skeleton(
        replace_fields(cfg, run=str(tmp_path / "straight")), progress=False, finalize=False
    )
    skel.train_skeleton(replace_fields(cfg, steps=3, run=str(tmp_path / "resumed")), progress=False)
    resumed = skel.train_skeleton(
        replace_fields(cfg, run=str(tmp_path / "resumed")),
        resume=True,
        progress=False,
        finalize=False,
    )
    graphdef, state = skel.build(cfg)
    assert set(state) == {"model", "opt", "ema"}
    restored = _restored_equal(tmp_path, skel.abstract_state(state), step=6)
    assert straight.validation["val/loss"] == pytest.approx(
        resumed.validation["val/loss"], rel=1e-5
    )
    # The exported detector carries the average, not the last weights.
    state = restored["straight"]
    exported, _ = trained.restore_detector(tmp_path / "straight", step=6)
    last = nnx.merge(graphdef, state["model"])
    average = optax.tree.bias_correction(state["ema"].ema, 0.5, state["ema"].count)
    got = jax.tree.leaves(nnx.state(exported, nnx.Param))
    for leaf, avg in zip(got, jax.tree.leaves(average), strict=True):
        np.testing.assert_allclose(leaf, avg, rtol=1e-6)
    weights = jax.tree.leaves(nnx.state(last, nnx.Param))
    assert any(not np.allclose(a, w) for a, w in zip(got, weights, strict=True))


def test_sequence_windows_pad_with_last_frame():
    frames = np.arange(7, dtype=np.float32)[:, None, None, None] * np.ones((7, 2, 2, 2))
    windows = trained.sequence_windows(frames, 3)
    assert windows.shape == (3, 3, 2, 2, 2)
    np.testing.assert_array_equal(windows[:, :, 0, 0, 0].ravel(), [0, 1, 2, 3, 4, 5, 6, 6, 6])


def test_nan_loss_stops_with_step_and_keeps_last_good_checkpoint(three_sequences, tmp_path):
    cfg = _cfg(three_sequences)

    with pytest.raises(skel.NonFiniteLossError, match="at step 3"):
        skel.train_skeleton(
            replace_fields(cfg, run=str(tmp_path / "run")),
            progress=False,
            finalize=False,
            step_hook=poison_after(2),
        )
    graphdef, state = skel.build(cfg)
    with checkpoints.Checkpointer(tmp_path / "run" / "checkpoints", keep=3) as ckpt:
        assert ckpt.latest_step() == 2
        _, good = ckpt.restore(skel.abstract_state(state))
    assert all(np.all(np.isfinite(x)) for x in _leaves(good))


def test_nan_found_between_log_steps_names_its_step_and_saves_nothing_after(
    three_sequences, tmp_path
):
    # Metrics are fetched at log / checkpoint steps only (4 and 2 here); the NaN of step 3 is
    # found at step 4 and reported as step 3, before step 4 could be checkpointed.
    cfg = _cfg(three_sequences, log_every=4, val_every=6, ckpt_every=2)

    with pytest.raises(skel.NonFiniteLossError, match="at step 3"):
        skel.train_skeleton(
            replace_fields(cfg, run=str(tmp_path / "run")),
            progress=False,
            finalize=False,
            step_hook=poison_after(2),
        )
    assert run_folder.checkpoint_steps(tmp_path / "run") == [2]
    assert not (tmp_path / "run" / run_folder.METRICS_FILE).exists()  # nothing logged before 4


def test_time_limit_stops_after_the_current_step_as_a_last_step(three_sequences, tmp_path):
    # A limit that has passed once the first step ends: that step is the last one, validated,
    # checkpointed and finalised like step `steps` would be.
    cfg = _cfg(three_sequences, time_limit_minutes=1e-9, log_every=5, val_every=5, ckpt_every=5)
    summary = skel.train_skeleton(replace_fields(cfg, run=str(tmp_path / "run")), progress=False)
    # The entry leaves a complete phase-1 run: the skeleton and the keypoints of both splits.
    assert (tmp_path / "run" / run_folder.SKELETON_FILE).is_file()
    for split in run_folder.SPLITS:
        assert run_folder.keypoints_file(tmp_path / "run", split).is_file()
    assert summary.step == 1 and summary.stop_reason == "time_limit"
    assert "val/loss" in summary.validation
    with checkpoints.Checkpointer(tmp_path / "run" / "checkpoints", keep=3) as ckpt:
        assert ckpt.all_steps() == [1]
    assert (tmp_path / "run" / "skeleton.json").is_file()
    # The exporter can read another copy of the dataset and write elsewhere: same keypoints.
    again = trained.export_keypoints(
        tmp_path / "run", "test", data_root=three_sequences, path=tmp_path / "again.npz"
    )
    with np.load(again) as a, np.load(tmp_path / "run" / "keypoints_test.npz") as b:
        assert sorted(a.files) == sorted(b.files)
        for name in a.files:
            np.testing.assert_array_equal(a[name], b[name])
    full = skel.train_skeleton(
        replace_fields(_cfg(three_sequences), run=str(tmp_path / "full")),
        progress=False,
        finalize=False,
    )
    assert full.step == 6 and full.stop_reason == "steps"


@pytest.mark.parametrize(
    ("override", "match"),
    [
        ("time_limit_minutes=-1", "time_limit_minutes"),
        ("ema_decay=1", "ema_decay"),
        ("model.num_keypoints=1", "num_keypoints"),
        ("model.grid=18", "multiple of 4"),
        ("data.frames=2", "frames"),
        ("model.keypoint_temperature=0", "keypoint_temperature"),
        ("data.rotate_degrees=270", "rotate_degrees"),
        ("data.grid=8", "data.grid"),
        ("model.nonsense=3", "no field 'nonsense'"),
        ("steps", "FIELD=VALUE"),
    ],
)
def test_bad_config_refused_before_anything_runs(tmp_path, capsys, override, match):
    run = tmp_path / "run"
    argv = ["train-skel", "--data", "synth-arm", "--preset", "tiny", "--run", str(run)]
    assert nmjax_main([*argv, "--set", override]) == 2
    err = capsys.readouterr().err
    assert match in err and len(err.strip().splitlines()) == 1
    assert not run.exists()


def test_unknown_data_lists_valid_names(capsys):
    assert nmjax_main(["train-skel", "--data", "nope"]) == 2
    err = capsys.readouterr().err
    assert "'nope'" in err and "synth-hand" in err and "hanco" in err


def test_overrides_parse_types():
    cfg = config_io.apply_overrides(
        skel_preset("synth-arm", "tiny"),
        [
            "model.channels=16",
            "weights.vol=0.5",
            "lr_milestones=3,7",
            "weights.intensity_weighted=1",
        ],
    )
    assert cfg.model.channels == 16 and cfg.weights.vol == 0.5
    assert cfg.optim.lr_milestones == (3, 7) and cfg.weights.intensity_weighted is True


def test_existing_run_refused_and_corrupt_checkpoint_left_untouched(three_sequences, tmp_path):
    cfg = _cfg(three_sequences, steps=2)
    run = tmp_path / "run"
    skel.train_skeleton(replace_fields(cfg, run=str(run)), progress=False, finalize=False)
    with pytest.raises(ValueError, match="--resume"):
        skel.train_skeleton(replace_fields(cfg, run=str(run)), progress=False, finalize=False)
    blobs = [
        p for p in (run / "checkpoints" / "2").rglob("*") if p.is_file() and p.parent.name == "d"
    ]
    assert blobs
    for p in blobs:
        p.write_bytes(b"not a checkpoint")
    files = {p: p.read_bytes() for p in (run / "checkpoints").rglob("*") if p.is_file()}
    # Restoring a corrupt checkpoint leaves orbax's tensorstore reads calling into a closed event
    # loop later (unraisable noise under pytest), so the command runs in its own process (with no
    # time limit: a loaded machine may take long to start it).
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "nmjax.cli",
            "train-skel",
            "--run",
            str(run),
            "--resume",
            "--steps",
            "4",
            "--no-progress",
        ],
        capture_output=True,
        text=True,
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
    )
    assert result.returncode == 2, result.stderr[-2000:]
    assert "checkpoint 2" in result.stderr and "corrupt" in result.stderr
    assert {p: p.read_bytes() for p in (run / "checkpoints").rglob("*") if p.is_file()} == files


def test_fit_schedule_scales_steps_and_milestones_to_the_budget():
    cfg = replace_fields(skel_preset("synth-arm", "tiny"), steps=20, lr_milestones=(10, 15))
    # 15 s at 1 s per step plus 20% overhead: 12 steps, the milestones at half and 3/4 of them.
    fitted = config.fit_schedule(cfg, 1.0, 0.25, overhead=0.2)
    assert (fitted.loop.steps, fitted.optim.lr_milestones) == (12, (6, 9))
    assert fitted.loop.time_limit_minutes == pytest.approx(0.25)
    # What the timing spent comes off the budget, for the steps and the stop alike.
    fitted = config.fit_schedule(cfg, 1.0, 0.25, spent_seconds=3.0, overhead=0.2)
    assert (fitted.loop.steps, fitted.optim.lr_milestones) == (10, (5, 8))
    assert fitted.loop.time_limit_minutes == pytest.approx(0.2)
    assert fitted.model == cfg.model and fitted.weights == cfg.weights
    # A faster step than the preset assumed buys more steps than the preset's.
    assert config.fit_schedule(cfg, 0.5, 60.0, overhead=0.0).loop.steps == 7200
    with pytest.raises(ValueError, match="fit only 0 steps"):
        config.fit_schedule(cfg, 10.0, 0.1)
    with pytest.raises(ValueError, match="seconds_per_step > 0"):
        config.fit_schedule(cfg, 0.0, 10.0)


def test_fit_minutes_times_the_step_and_trains_the_fitted_schedule(
    data_root, tmp_path, monkeypatch, capsys
):
    from nmjax import bench

    timed = []

    # A 100 s step, whatever this machine does: the fitted 22 minutes are far more than the 12
    # tiny steps take on a loaded machine, so the time limit cannot cut the run short.
    def fake_bench(cfg, preset, steps, warmup):
        timed.append(cfg)
        return {"compute_s_median": 99.8, "load_s_per_step": 0.2}

    monkeypatch.setattr(bench, "bench_skel", fake_bench)
    run = tmp_path / "run"
    small = ["data.grid=8", "model.grid=8", "data.frames=3", "data.batch_size=1"]
    small += ["model.channels=4", "model.num_keypoints=4", "model.hourglass_channels=4,4,4"]
    small += ["val_batches=1", "lr_milestones=10,15"]
    argv = ["train-skel", "--data", "synth-arm", "--preset", "tiny", "--root", str(data_root)]
    argv += ["--run", str(run), "--no-progress", *(a for s in small for a in ("--set", s))]
    assert nmjax_main([*argv, "--fit-minutes", "22"]) == 0
    # 1,320 s / (100 s x 1.08) = 12.2 steps; the milestones 10 and 15 of 20 scale with them.
    saved = json.loads((run / "config.json").read_text())
    assert (saved["loop"]["steps"], tuple(saved["optim"]["lr_milestones"])) == (12, (6, 9))
    assert 21.5 < saved["loop"]["time_limit_minutes"] <= 22.0
    assert len(timed) == 1 and timed[0].loop.steps == 20 and timed[0].model.grid == 8
    assert "12 steps" in capsys.readouterr().err
    assert (run / "checkpoints" / "12").exists()
    # The schedule is fixed at the start: with --steps or --resume the option is refused.
    for extra in (["--steps", "5"], ["--resume"]):
        assert nmjax_main([*argv, "--fit-minutes", "22", *extra]) == 2
        assert "--fit-minutes" in capsys.readouterr().err


def test_init_from_starts_a_new_run_from_the_source_weights(three_sequences, tmp_path, capsys):
    """A run fine-tuned from another (`init_from`): its first step's loss is the source
    detector's loss on that batch, its optimizer is fresh, its config.json names the source; a
    network of another K is refused in one line before anything is written."""
    from nmjax.data import pipeline

    cfg = _cfg(three_sequences, steps=2)
    source = tmp_path / "source"
    skel.train_skeleton(replace_fields(cfg, run=str(source)), progress=False, finalize=False)
    tuned = replace_fields(cfg, steps=1, init_from=str(source))
    skel.train_skeleton(
        replace_fields(tuned, run=str(tmp_path / "tuned")), progress=False, finalize=False
    )

    def first_loss(run):
        return next(r["train/loss"] for r in metric_log.read_metrics(run) if "train/loss" in r)

    # The source detector's loss (Eq. 23, by the trainer's own compiled validation step) on the
    # batch of the first step: the same data and seed give the same first crop.
    resolved = config.resolve_epochs(tuned, 2, 1)  # as the trainer resolves it
    graphdef, state = skel.build(resolved)
    mesh = parallel.data_mesh()
    weights = {**state, "model": nnx.state(trained.restore_detector(source)[0])}
    batch = next(pipeline.skel_iterator(cfg.data, "train", seed=cfg.seed))
    _, eval_fn = skel.make_steps(graphdef, resolved, mesh)
    terms, _ = eval_fn(
        parallel.replicate(weights, mesh), skel.device_batch(batch, cfg, mesh, host_slice=False)
    )
    expected = float(terms["loss"])
    assert first_loss(tmp_path / "tuned") == pytest.approx(expected, rel=1e-5)
    # The source's own first step, from the seed's initialisation, saw another loss.
    assert first_loss(source) != pytest.approx(expected, rel=1e-5)
    with checkpoints.Checkpointer(tmp_path / "tuned" / "checkpoints", keep=3) as ckpt:
        _, restored = ckpt.restore(skel.abstract_state(state), step=1)
    counts = [
        int(x)
        for path, x in jax.tree_util.tree_leaves_with_path(restored["opt"])
        if "count" in jax.tree_util.keystr(path)
    ]
    assert counts and set(counts) == {1}  # one update since the optimizer was made
    saved = json.loads((tmp_path / "tuned" / "config.json").read_text())
    assert saved["init_from"] == str(source)

    argv = ["train-skel", "--data", "synth-arm", "--root", str(three_sequences), "--preset"]
    argv += ["tiny", "--run", str(tmp_path / "k5"), "--init-from", str(source), "--no-progress"]
    for change in ("data.grid=8", "model.grid=8", "model.channels=4", "model.num_keypoints=5"):
        argv += ["--set", change]
    assert nmjax_main([*argv, "--set", "model.hourglass_channels=4,4,4"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    assert "model.num_keypoints (run: 4, asked: 5)" in lines[0]
    assert "--set model.num_keypoints=4" in lines[0] and "model.channels" not in lines[0]
    assert not (tmp_path / "k5").exists()
    resume = ["train-skel", "--run", str(source), "--resume", "--init-from", str(source)]
    assert nmjax_main(resume) == 2
    assert "give one of them" in capsys.readouterr().err
