"""Tests of nmjax.train.dyn (and the phase-2 side of nmjax.train.trained) on a fake phase-1 run
(a known tree moved by smooth rotations)."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx
from tiny_configs import fake_run_dyn_config as tiny_cfg
from tiny_configs import small_skel_config
from tiny_runs import FAKE_ORDER as ORDER
from tiny_runs import FAKE_PARENTS as PARENTS
from tiny_runs import spread_convolutions

from nmjax import atomic, run_folder
from nmjax.cli import main as nmjax_main
from nmjax.cli.train import train_config, train_parser
from nmjax.config import DynamicsConfig, dyn_preset
from nmjax.config_io import replace_fields
from nmjax.data.datasets import Sequence
from nmjax.data.normalize import normalize_sequence
from nmjax.data.voxelize import voxelize
from nmjax.models.detector import KeypointDetector
from nmjax.models.dynamics import Dynamics, bone_lengths
from nmjax.train import checkpoints, dyn, dyn_inputs, metric_log, trained

K = len(PARENTS)


def test_missing_inputs_name_the_command_to_run(tmp_path):
    with pytest.raises(FileNotFoundError, match="make train-skel DATA=synth-arm"):
        run_folder.find_skel_run("synth-arm", runs_root=tmp_path)
    run = tmp_path / "skel-synth-arm-1"
    run.mkdir()
    assert run_folder.find_skel_run("synth-arm", runs_root=tmp_path) == run
    with pytest.raises(FileNotFoundError, match=re.escape(f"nmjax extract-skeleton --run {run}")):
        run_folder.read_skeleton(run)
    atomic.write_json(run / "skeleton.json", {"parents": [1, 0], "order": [0, 1]})
    with pytest.raises(ValueError, match="extract-skeleton"):
        run_folder.read_skeleton(run)
    # A missing export is an error naming the command, never a hidden phase-1 inference.
    with pytest.raises(FileNotFoundError, match=re.escape(f"nmjax export-keypoints --run {run}")):
        run_folder.load_trajectories(run, "train")
    assert not list(run.glob("keypoints_*"))


def test_main_reports_missing_phase1_run(tmp_path, capsys):
    argv = ["train-dyn", "--data", "synth-arm", "--skel-run", str(tmp_path / "nope")]
    assert nmjax_main([*argv, "--preset", "tiny"]) == 2
    err = capsys.readouterr().err
    assert "make train-skel DATA=synth-arm" in err and len(err.strip().splitlines()) == 1


def test_trajectories_beyond_float32_are_refused(tmp_path):
    np.savez(tmp_path / "k.npz", seq=np.full((3, 2, 4), 1e300))
    with pytest.raises(ValueError, match="float32 range"):
        run_folder.read_trajectories(tmp_path / "k.npz")


def test_crops_are_contiguous_windows_of_one_sequence(fake_run):
    traj = run_folder.load_trajectories(fake_run, "train")
    poses, starts = dyn_inputs.crop_table(traj, 6)
    # valid starts: 30-6+1 + 25-6+1 + 1 (the 4-frame sequence padded to 6)
    assert len(starts) == 25 + 20 + 1 and poses.shape == (30 + 25 + 6, K, 4)
    draws = dyn.CropDraws(jax.random.key(0), len(starts), batch_size=4, block=8)
    chosen = np.concatenate([draws.at(step) for step in range(16)])  # two blocks
    assert chosen.min() >= 0 and chosen.max() < len(starts) and len(set(chosen.tolist())) > 20
    # A step's draws are the same whichever block computed them (exact resume).
    np.testing.assert_array_equal(
        dyn.CropDraws(jax.random.key(0), len(starts), batch_size=4, block=3).at(9), chosen[36:40]
    )
    crops = dyn_inputs.CropTable(poses, starts, 6).batch(chosen)
    windows = {
        name: np.lib.stride_tricks.sliding_window_view(x, 6, axis=0).transpose(0, 3, 1, 2)
        for name, x in traj.items()
        if len(x) >= 6
    }
    short = traj["train2"]
    padded = np.concatenate([short, np.repeat(short[-1:], 2, axis=0)])
    for crop in crops:
        found = any(np.any(np.all(w == crop, axis=(1, 2, 3))) for w in windows.values())
        assert found or np.array_equal(crop, padded)


def jaxpr_stats(jaxpr) -> tuple[int, list[int]]:
    """(number of equations, counting nested jaxprs; lengths of all scans) of a jaxpr."""
    jaxpr = getattr(jaxpr, "jaxpr", jaxpr)
    count, scans = 0, []
    for eqn in jaxpr.eqns:
        count += 1
        if eqn.primitive.name == "scan":
            scans.append(eqn.params["length"])
        for value in eqn.params.values():
            for sub in value if isinstance(value, tuple | list) else (value,):
                if hasattr(sub, "eqns"):
                    sub_count, sub_scans = jaxpr_stats(sub)
                    count, scans = count + sub_count, scans + sub_scans
    return count, scans


def test_train_step_scans_over_time_and_compiles_once(fake_run, tmp_path, monkeypatch):
    def trace(frames):
        cfg = tiny_cfg(fake_run, tmp_path, frames=frames)
        graphdef, state = dyn.build(cfg, PARENTS, ORDER)
        poses, starts = dyn_inputs.crop_table(
            run_folder.load_trajectories(fake_run, "train"), frames
        )
        x = dyn_inputs.CropTable(poses, starts, frames).batch(np.arange(cfg.data.batch_size))
        step = dyn.make_train_step(graphdef, cfg)
        args = (state, jnp.asarray(x), jax.random.key(0), jnp.int32(0))
        return jaxpr_stats(jax.make_jaxpr(step)(*args)), step, args

    (count6, scans6), step, args = trace(6)
    (count12, scans12), _, _ = trace(12)
    assert 6 in scans6 and 12 in scans12  # forward (and backward) scans over time
    assert 12 not in scans6 and 6 not in scans12
    # No per-frame unrolling: doubling T does not add a single equation.
    assert count6 == count12

    # At most one trace for all the calls below (none if make_jaxpr's trace is reused).
    monkeypatch.setattr(dyn, "loss_fn", chex.assert_max_traces(dyn.loss_fn, n=1))
    state = args[0]
    for i in range(3):
        state, metrics = step(state, *args[1:3], jnp.int32(i))
    # A second model of the same configuration reuses the compiled step (no second trace).
    graphdef, fresh = dyn.build(tiny_cfg(fake_run, tmp_path, frames=6), PARENTS, ORDER)
    dyn.make_train_step(graphdef, tiny_cfg(fake_run, tmp_path, frames=6))(
        fresh, *args[1:3], jnp.int32(0)
    )
    assert all(np.isfinite(float(v)) for v in metrics.values())


def test_a_few_steps_reduce_the_loss_on_a_fixed_batch(fake_run, tmp_path):
    cfg = tiny_cfg(fake_run, tmp_path)
    graphdef, state = dyn.build(cfg, PARENTS, ORDER)
    frames = cfg.data.frames
    poses, _ = dyn_inputs.crop_table(run_folder.load_trajectories(fake_run, "train"), frames)
    x = jnp.asarray(np.repeat(poses[None, 3 : 3 + frames], cfg.data.batch_size, 0))  # fixed batch
    step = dyn.make_train_step(graphdef, cfg)
    recon = []
    for i in range(60):
        state, metrics = step(state, x, jax.random.key(2), jnp.int32(i))
        recon.append(float(metrics["recon"]))  # Eq. 3 before this step's update
    assert np.mean(recon[-5:]) < 0.5 * np.mean(recon[:5])
    crop = poses[3 : 3 + frames]  # the logged baseline: x_t predicted by x_{t-1}
    expected = np.mean(np.sum(np.square(crop[1:] - crop[:-1]), axis=(-2, -1)))
    np.testing.assert_allclose(float(metrics["last_pose"]), expected, rtol=1e-5)


def test_phase2_kl_is_the_mean_of_the_per_dimension_kl(fake_run):
    """The release's reduction: mean over batch, time and latent dimension (not summed over D_z)."""
    cfg = DynamicsConfig(latent=4, hidden=8, mlp=8, posterior_samples=2)
    model = Dynamics(cfg, PARENTS, ORDER, rngs=nnx.Rngs(0))
    x = jnp.asarray(
        dyn_inputs.validation_crops(run_folder.load_trajectories(fake_run, "train"), 6)[:3]
    )
    key = jax.random.key(1)
    _, metrics = dyn.loss_fn(model, x, key, 0.5)
    out = model(x, key)
    mq, sq, mp, sp = (np.asarray(a, np.float64) for a in out[3:])  # (B, T, D_z) each
    per_dimension = np.log(sp / sq) + (sq**2 + (mq - mp) ** 2) / (2 * sp**2) - 0.5
    assert per_dimension.shape == (3, 6, 4)
    np.testing.assert_allclose(float(metrics["kl"]), per_dimension.mean(), rtol=1e-5)
    np.testing.assert_allclose(
        float(metrics["loss"]), float(metrics["recon"]) + 0.5 * per_dimension.mean(), rtol=1e-5
    )


def test_resume_equals_uninterrupted_training(fake_run, tmp_path):
    cfg = tiny_cfg(fake_run, tmp_path / "full", steps=4, ckpt_every=4, val_every=4, log_every=1)
    full = dyn.train_dynamics(cfg, progress=False)
    stopped = replace_fields(cfg, run=str(tmp_path / "half"), steps=2)
    dyn.train_dynamics(stopped, progress=False)
    half = dyn.train_dynamics(replace_fields(stopped, steps=4), resume=True, progress=False)
    run_full, run_half = full.run, half.run
    full_state = nnx.state(trained.restore_dynamics(run_full))
    half_state = nnx.state(trained.restore_dynamics(run_half))
    for a, b in zip(jax.tree.leaves(full_state), jax.tree.leaves(half_state), strict=True):
        np.testing.assert_array_equal(a, b)
    assert half.validation == full.validation and half.step == full.step == 4
    records = [r for r in metric_log.read_metrics(run_half) if "train/loss" in r]
    expected = [r for r in metric_log.read_metrics(run_full) if "train/loss" in r]
    assert [r["step"] for r in records] == [1, 2, 3, 4]
    assert [r["train/loss"] for r in records] == [r["train/loss"] for r in expected]


def test_command_trains_logs_and_generates_with_skeleton_bone_lengths(fake_run, tmp_path, capsys):
    run = tmp_path / "cli"
    argv = ["--data", "synth-arm", "--skel-run", str(fake_run), "--preset", "tiny"]
    argv += ["--set", "data.inputs=sequence"]
    assert nmjax_main(["train-dyn", *argv, "--steps", "10", "--run", str(run)]) == 0
    assert "final validation" in capsys.readouterr().out
    saved = json.loads((run / "config.json").read_text())
    assert saved["skel_run"] == str(fake_run) and saved["model"]["model"] == "nm"
    records = metric_log.read_metrics(run)
    val = [r for r in records if "val/recon" in r]
    assert [r["step"] for r in val] == [5, 10]
    assert all(np.isfinite(v) for r in records for v in r.values())
    assert sorted(p.name for p in (run / "figures").glob("*.png")) == [
        "motion_0000005.png",
        "motion_0000010.png",
    ]
    assert any((run / "tb").iterdir())
    with pytest.raises(ValueError, match="--resume"):
        dyn.train_dynamics(dyn_config(parse_dyn([*argv, "--run", str(run)])), progress=False)

    model = trained.restore_dynamics(run)
    x = jnp.asarray(dyn_inputs.validation_crops(run_folder.load_trajectories(fake_run, "test"), 6))
    keypoints, rotations = model.generate(x[:, :2], 10, jax.random.key(0))
    assert keypoints.shape == (x.shape[0], 12, K, 4) and rotations.shape[-2:] == (3, 3)
    assert bool(jnp.all(jnp.isfinite(keypoints)))
    lengths = np.linalg.norm(keypoints[..., :3] - keypoints[..., PARENTS, :3], axis=-1)
    offsets = np.linalg.norm(model.offsets(bone_lengths(x[:, :2], PARENTS)), axis=-1)
    np.testing.assert_allclose(lengths, np.broadcast_to(offsets[:, None], lengths.shape), atol=1e-5)


def parse_dyn(argv):
    return train_parser("dyn").parse_args(argv)


def dyn_config(args):
    return train_config(args, "dyn")


def test_command_line_options_map_onto_the_config():
    cfg = dyn_config(
        parse_dyn(["--data", "synth-hand", "--model", "vrnn", "--preset", "cpu", "--steps", "7"])
    )
    assert cfg.model.model == "vrnn" and cfg.loop.steps == 7
    assert cfg.model.hidden == dyn_preset("synth-hand", "cpu").model.hidden
    # --steps on the default preset (in epochs) turns the run into a step count.
    cfg = dyn_config(parse_dyn(["--steps", "50"]))
    assert (cfg.loop.epochs, cfg.loop.steps, cfg.optim.optimizer_reset) == (0, 50, "epoch")
    assert dyn_config(parse_dyn([])).loop.epochs == 150
    cfg = dyn_config(parse_dyn(["--set", "kl_weight=1e-5", "--set", "model.latent=8"]))
    assert cfg.kl_weight == 1e-5 and cfg.model.latent == 8 and cfg.model.model == "nm"
    with pytest.raises(ValueError, match="no_such_field"):  # an unknown field is named
        dyn_config(parse_dyn(["--set", "model.no_such_field=1"]))
    with pytest.raises(ValueError, match="--resume needs --run"):
        dyn_config(parse_dyn(["--resume"]))


# --- "crop" inputs: every crop normalised on its own and run through the detector --------------


def translated_body(frames: int = 9) -> Sequence:
    """A rigid blob of points walking 2 units along x (about twice its size) over the sequence."""
    rng = np.random.default_rng(0)
    body = rng.normal(size=(400, 3)) * np.array([0.3, 0.2, 0.5])
    shift = np.linspace(0.0, 2.0, frames)[:, None, None] * np.array([1.0, 0.0, 0.0])
    return Sequence("walk", (body[None] + shift).astype(np.float32), None, Path("walk.npy"))


def test_crop_inputs_are_the_detector_on_each_crop_normalised_on_its_own(tmp_path):
    cfg = small_skel_config(tmp_path)  # an untrained detector: G=8, K=4, phase-1 T=3
    model = KeypointDetector(cfg.model, rngs=nnx.Rngs(0))
    spread_convolutions(model)  # keypoints that follow the body, as a trained detector's do
    detector = trained.Detector.of(model, cfg, tmp_path)
    seq, frames, grid = translated_body(), 4, cfg.data.grid
    crop = dyn_inputs.crop_inputs(detector, [seq], [seq], frames)
    assert crop.crops.num_starts == 6 and crop.crops.detected == 0  # every start of the 9 frames

    # "sequence": one box over the walk, the detector on consecutive windows (export_keypoints).
    whole = trained.sequence_voxels(seq, cfg.data.sample_rate, grid)
    windows = detector.keypoints(trained.sequence_windows(whole, cfg.data.frames))
    trajectory = windows.reshape(-1, *windows.shape[2:])[: seq.num_frames]
    cut = dyn_inputs.sequence_inputs(
        {"train": {"walk": trajectory}, "test": {"walk": trajectory}}, frames
    )

    def crop_at(inputs, s):
        return inputs.crops.batch(np.array([s]))[0]

    for s in (0, 5):
        own, _ = normalize_sequence(seq.vertices[s : s + frames])
        direct = detector.keypoints(voxelize(own, grid)[None])[0]
        np.testing.assert_allclose(crop_at(crop, s), direct, atol=1e-6)
        assert np.abs(crop_at(cut, s)[..., :3] - direct[..., :3]).max() > 0.03
    # Normalised on itself, a translated crop is the same crop; in the sequence's box it is not.
    np.testing.assert_allclose(crop_at(crop, 0), crop_at(crop, 5), atol=1e-6)
    assert np.abs(crop_at(cut, 0) - crop_at(cut, 5)).max() > 0.03

    # Validation: the first crop, and its first T_cond frames detected alone for generation.
    own, _ = normalize_sequence(seq.vertices[:frames])
    voxels = voxelize(own, grid)[None]
    np.testing.assert_allclose(crop.val[0], detector.keypoints(voxels)[0], atol=1e-6)
    t_cond = dyn_inputs.condition_frames(frames)
    assert crop.val_cond.shape == (len(crop.val), t_cond, 4, 4)
    np.testing.assert_allclose(
        crop.val_cond[0], detector.keypoints(voxels[:, :t_cond])[0], atol=1e-6
    )


def test_validation_generates_from_the_given_conditioning_keypoints(fake_run):
    model = Dynamics(
        DynamicsConfig(latent=4, hidden=8, mlp=8, posterior_samples=2),
        PARENTS,
        ORDER,
        rngs=nnx.Rngs(0),
    )
    x = jnp.asarray(dyn_inputs.validation_crops(run_folder.load_trajectories(fake_run, "test"), 6))
    other = x[:, :1] + 0.5  # conditioning keypoints that differ from the crop's own
    key = jax.random.key(0)
    metrics, generated = dyn.evaluate(model, x, other, key)
    expected, _ = model.generate(other, x.shape[1] - 1, jax.random.split(key, 3)[2])
    np.testing.assert_allclose(generated, expected, atol=1e-6)
    hold = np.mean(np.sum((np.asarray(x[:, 1:]) - np.asarray(other)) ** 2, axis=(-2, -1)))
    np.testing.assert_allclose(float(metrics["gen_hold"]), hold, rtol=1e-5)


def test_init_from_starts_from_the_source_model_and_checks_its_network(fake_run, tmp_path, capsys):
    """`init_from`: the new run's first step sees the source run's trained weights and a fresh
    optimizer, config.json names the source; another network width is refused in one line, as
    is resuming a folder of imported weights (checkpoint 0 only)."""
    cadence = dict(steps=2, ckpt_every=2, val_every=2, log_every=1)
    source_cfg = tiny_cfg(fake_run, tmp_path / "source", **cadence)
    dyn.train_dynamics(source_cfg, progress=False)
    source = jax.tree.leaves(nnx.state(trained.restore_dynamics(tmp_path / "source")))
    seen = {}

    def hook(step, state):
        seen.setdefault(step, jax.device_get(state))
        return state

    tuned = dataclasses.replace(
        source_cfg, run=str(tmp_path / "tuned"), init_from=str(tmp_path / "source")
    )
    dyn.train_dynamics(tuned, progress=False, step_hook=hook)
    for a, b in zip(jax.tree.leaves(seen[0]["model"]), source, strict=True):
        np.testing.assert_array_equal(a, b)
    assert not any(np.any(x) for x in jax.tree.leaves(seen[0]["opt"]))  # Adam's zero state
    saved = json.loads((tmp_path / "tuned" / "config.json").read_text())
    assert saved["init_from"] == str(tmp_path / "source")

    argv = ["train-dyn", "--data", "synth-arm", "--skel-run", str(fake_run), "--preset", "tiny"]
    argv += ["--set", "data.inputs=sequence", "--run", str(tmp_path / "w")]
    wider = ["--set", "model.hidden=32", "--init-from", str(tmp_path / "source")]
    assert nmjax_main([*argv, *wider]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "model.hidden (run: 16, asked: 32)" in lines[0], lines
    assert nmjax_main([*argv, "--init-from", str(fake_run)]) == 2  # a phase-1 folder
    assert "no config.json" in capsys.readouterr().err
    assert not (tmp_path / "w").exists()

    imported = run_folder.prepare_run_dir(tmp_path / "imported", resume=False, config=tuned)
    with checkpoints.Checkpointer(imported / "checkpoints", 1) as ckpt:
        ckpt.save(0, seen[0])  # what `nmjax import-release` writes: weights, untouched Adam
    assert nmjax_main(["train-dyn", "--run", str(imported), "--resume"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and f"--init-from {imported}" in lines[0], lines


def test_an_aist_sized_crop_run_detects_fewer_crops_than_the_release():
    """experiments/phase2_inputs_cost.py's count: at the default preset phase 2 on AIST++ draws
    150 epochs x ceil(1,227 / 16) x 16 crops; the distinct starts among them, each detected
    once, are fewer than the release's one crop per sequence per epoch, and far fewer than every
    start up front."""
    from experiment_scripts import load_experiment

    count = load_experiment("phase2_inputs_cost.py").aist_count(800)
    assert count["training_sequences"] == 1227 and count["release_detected"] == 150 * 1227
    assert count["draws"] == 150 * 77 * 16 and count["crop_starts"] == 1227 * (800 - 39 + 1)
    assert count["expected_detected"] < count["release_detected"] < count["up_front_detected"]
    assert count["bound_detected"] == min(count["crop_starts"], count["draws"])
